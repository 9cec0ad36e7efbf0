"""What the API (``service``), the worker (``worker``) and the PACS gateway share: settings, the job database and
its schema, storage, the broker queue, safe logging, the job parameters a client sends (the job's contract), and
the PACS pieces a worker needs (settings, ``pacs_jobs`` records, the DICOMweb client).

``core`` imports the engine's Warp-free modules only (``engine.params``, ``engine.errors``), never ``service``,
``worker``, FastAPI/Starlette, or GPU code (Warp) at module level: ``service -> core -> engine`` and
``worker -> core, engine`` (``tests/test_import_contracts.py``).
"""
