"""The benchmark phantom lives in the engine (``engine.data.phantom``: ``bonemesh sweep --phantom`` needs it in an
installed package); this module keeps the benchmarks' import path."""

from engine.data.phantom import BONE_LEVEL, bone_phantom

__all__ = ["BONE_LEVEL", "bone_phantom"]
