"""nerfart_plugin: text-driven stylization of neural radiance fields.

After *NeRF-Art: Text-Driven Neural Radiance Fields Stylization* (Wang et al.,
TVCG 2023). Components (datamodules, backbones, encodings, guidance) are
registered by name in :mod:`nerfart_plugin.config.registry` and built from Hydra
configs in ``conf/``.
"""

__version__ = "0.1.0"
