"""Runners for the pipeline's plan: Celery tasks on Redis (``celery_app``) or an in-process pool (``embedded``)."""
