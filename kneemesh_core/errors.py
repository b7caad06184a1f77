"""The one exception type the library raises for bad input or impossible work.

Every error carries a stable machine-readable ``code`` (used by the CLI exit
message and, later, by the HTTP API) and a human message that says what is
wrong and what is expected.
"""

from __future__ import annotations


class KneeMeshError(Exception):
    """Bad input or a step that cannot be done, with a stable ``code``.

    Parameters
    ----------
    code : str
        Stable identifier, e.g. ``"not_an_image"``, ``"empty_labels"``.
    message : str
        What is wrong and what is expected, in one sentence or two.
    """

    def __init__(self, code: str, message: str):
        super().__init__(message)
        self.code = code
        self.message = message

    def __str__(self) -> str:  # pragma: no cover - trivial
        return self.message
