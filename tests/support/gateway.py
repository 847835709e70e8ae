"""Shared by the gateway tests: the token, the scene, the time bound of an episode (their fixtures ``fleet``
and ``gw_settings`` are in ``conftest.py``)."""

from __future__ import annotations

TOKEN = "test-token-1"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
SCENE = "gen-00001"
EPISODE_S = 120.0  # bound on the wall time of one short episode on a busy 2-core machine
# four tenants (two submitters, an admin, a reader) and a short question, for the multi-tenant suites
TOKENS = ["tok-a", "tok-b", "tok-admin:admin", "tok-reader:read"]
A = {"Authorization": "Bearer tok-a"}
B = {"Authorization": "Bearer tok-b"}
ADMIN = {"Authorization": "Bearer tok-admin"}
READER = {"Authorization": "Bearer tok-reader"}
Q = {"question": "Where is the black suitcase?", "choices": ["bedroom", "hallway"], "scene": SCENE, "max_steps": 3,
     "record": False}
