"""One module per stage: ``reconstruct``, ``stylize``, ``preview`` (training stages on the shared skeleton of
:mod:`~nerfart_plugin.run.stages.base`) and ``render``, ``export`` (read a finished run). Add a stage here and
name it in :data:`nerfart_plugin.run.pipeline.PLANS`."""
