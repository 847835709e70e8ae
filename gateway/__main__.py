"""``python -m gateway``: run the HTTP gateway on EQA_GATEWAY_HOST:EQA_GATEWAY_PORT.

A process entry point (composition root, application layer): it hands the simulator's scene library to the
gateway, which itself imports no service (``tests/kernel/test_layers.py``)."""

from gateway.cli import main
from services.sim.library import floor_area

raise SystemExit(main(scene_area=floor_area))
