"""Service tests: real redis-server, ``bonemesh serve`` and ``bonemesh worker`` processes."""
