"""The PACS pieces shared by the API, the gateway (``bonemesh pacs``) and the worker.

Modules: ``config`` (``BONEMESH_PACS_*`` settings), ``routing`` (which series become jobs: the rules of those
settings), ``records`` (the ``pacs_jobs`` table beside the job table: source, destination, delivery state),
``dicomweb`` (clients of configured servers: the worker's WADO-RS fetch, the gateway's STOW-RS delivery) and
``multipart`` (the multipart/related reader it uses). The API-side modules are in ``service.pacs``. Nothing here
imports Warp, FastAPI or the worker.
"""
