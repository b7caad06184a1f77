"""The API's routes, one module per resource: ``jobs``, ``artifacts``, ``batches``, ``operations``."""
