"""The project's benchmarks: each module measures one trade and writes its section of BENCHMARKS.md (and its raw
figures under ``benchmarks/results/``) from a real run. Run one from the repository root with
``python -m benchmarks NAME [options]`` (``python -m benchmarks`` lists them; ``NAME --help`` its options)."""
