"""Shared by the gateway tests: the token, the scene, the time bound of an episode (their fixtures ``fleet``
and ``gw_settings`` are in ``conftest.py``)."""

from __future__ import annotations

TOKEN = "test-token-1"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SCENE = "gen-00001"
EPISODE_S = 120.0  # bound on the wall time of one short episode on a busy 2-core machine
