"""The application layer: programs built on the kernel (:mod:`eqa`), the services and the gateway.

``eqa`` command line (``cli.py``), one question end to end (``ask.py``), the benchmark runner that drives many
questions through a fleet and collects their traces (``benchmark_runner.py``), conformal calibration
(``calibrate.py``), the paper's comparisons (``bench_cli.py``, ``evaluation.py``, ``plots.py``).
Nothing in the kernel, the services or the gateway imports this package (``tests/kernel/test_layers.py``).
"""
