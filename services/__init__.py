"""The KneeMesh service: a FastAPI API (``services.api``) and Celery workers (``services.worker``).

Both sides share the settings, the artifact store and the job records here;
the science is in ``kneemesh_core`` and the job itself is ``kneemesh_core.job``.
"""
