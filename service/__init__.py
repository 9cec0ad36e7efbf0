"""FastAPI service (filled by the "service + worker" issue). Never imports Warp."""
