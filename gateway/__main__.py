"""``python -m gateway``: run the HTTP gateway on EQA_GATEWAY_HOST:EQA_GATEWAY_PORT."""

from gateway.cli import main

raise SystemExit(main())
