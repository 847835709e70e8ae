"""One router per resource: episodes (authenticated) and health (open)."""
