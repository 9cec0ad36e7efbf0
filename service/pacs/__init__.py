"""Hospital PACS integration: receive CT series by DICOM C-STORE (``bonemesh pacs``) or pull them over DICOMweb
(``POST /v1/jobs`` with a ``source``), run them as ordinary jobs, and send the model back as Encapsulated STL.

Modules: ``config`` (``BONEMESH_PACS_*`` settings), ``routing`` (which series become jobs), ``records`` (the
``pacs_jobs`` table beside the job table: source, destination, delivery state), ``inbox`` (instances grouped by
study/series on disk until a series is stable), ``scp`` (the storage SCP), ``delivery`` (C-STORE / STOW-RS with
retries), ``dicomweb`` (clients of configured servers), ``api`` (the DICOMweb job request), ``gateway`` (the
``bonemesh pacs`` process). Nothing here imports Warp or the worker.
"""
