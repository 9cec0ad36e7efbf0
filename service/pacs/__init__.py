"""Hospital PACS integration: receive CT series by DICOM C-STORE (``bonemesh pacs``) or pull them over DICOMweb
(``POST /v1/jobs`` with a ``source``), run them as ordinary jobs, and send the model back as Encapsulated STL.

Modules: ``inbox`` (instances grouped by study/series on disk until a series is stable), ``scp`` (the storage
SCP), ``delivery`` (C-STORE / STOW-RS with retries), ``models`` (the DICOMweb job request's body), ``api`` (that
request), ``gateway`` (the ``bonemesh pacs`` process). The settings, routing rules, ``pacs_jobs`` records and the
DICOMweb client are shared with the worker and live in :mod:`core.pacs`. Nothing here imports Warp or the worker.
"""
