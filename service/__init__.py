"""The bonemesh web service (FastAPI): jobs, uploads, signed downloads. Never imports Warp or the worker."""
