"""Component benchmarks and studies that print figures (never timed assertions in tests): one module each,
``python -m eqa_app.benches.<name> --help``; :mod:`eqa_app.benches.harness` holds what they share."""
