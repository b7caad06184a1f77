"""``kneemesh`` command line: the same pipeline as the service, run in-process, and the lab's cohort tools.

One module per area, each adding its commands to :data:`.app.app`: :mod:`.knee` (inspect, phantom,
mesh, run, simulate), :mod:`.segmentation` (segment, evaluate-seg, train), :mod:`.cohort` (submit,
compare, report), :mod:`.service` (serve, worker, cleanup, openapi); :mod:`.render` prints the tables.
"""

# each module registers its commands, listed by --help in this order
from kneemesh.cli import knee  # noqa: F401,I001
from kneemesh.cli import segmentation  # noqa: F401
from kneemesh.cli import cohort  # noqa: F401
from kneemesh.cli import service  # noqa: F401
from kneemesh.cli.app import app, entry

__all__ = ["app", "entry"]
