"""The ``kneemesh`` Typer application, its consoles, and what every command shares: one-line errors,
the flags of :class:`kneemesh_core.job.JobRequest`, the exit without teardown."""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
import sys
import threading
from contextlib import contextmanager
from inspect import Parameter, signature
from typing import Optional

import typer

from kneemesh.console import console
from kneemesh_core import KneeMeshError, __version__
from kneemesh_core.job import JobRequest

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Knee MRI or label maps to FE-ready knee models.")
out = console()
err = console(stderr=True)


def entry() -> None:
    """The ``kneemesh`` command: :data:`app`, then out of the process without the interpreter's
    teardown once nothing is left running.  By then every output is written; freeing the
    meshing libraries' modules and objects would add about 0.4 s to each knee of a cohort run
    knee by knee (``kneemesh mesh``)."""
    try:
        app()
        code = 0
    except SystemExit as exc:  # click ends every command this way, with the exit status
        if threading.active_count() > 1 or not isinstance(exc.code, (int, type(None))):
            raise  # a thread still running, or a message to print: Python's own exit
        code = exc.code or 0
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


@contextmanager
def clear_errors():
    """Bad input ends in one red line and a non-zero exit, never a traceback."""
    try:
        yield
    except KneeMeshError as exc:
        err.print(f"[bold red]error[/] ({exc.code}): {exc.message}", highlight=False, soft_wrap=True)
        raise typer.Exit(2)


def job_option(field: str, *flags: str):
    """A command-line flag for one option of :class:`JobRequest`, with its help and default from
    there (the flag's own default is None: not given, so the request's default applies)."""
    f = JobRequest.model_fields[field]
    default = "" if f.default is None else f" (default: {f.default})"
    return typer.Option(None, *flags, help=f"{f.description}{default}", show_default=False)


PresetOpt = job_option("preset", "--preset")
LabelsOpt = typer.Option(None, "--labels", help="Custom mapping 'femur=5,tibia=6,...' or a JSON file.")
SideOpt = job_option("side", "--side")
WorkersOpt = typer.Option(2, "--workers", min=1, help="Processes meshing tissues in parallel.")
#: The meshing flags `mesh`, `run` and `submit` share: name -> (type, flag).
MESH_FLAGS = {
    "only": (Optional[str], job_option("only", "--only")),
    "stl": (Optional[bool], job_option("stl", "--stl/--no-stl")),
    "bone_edge": (Optional[float], job_option("bone_edge", "--bone-edge")),
    "element_size": (Optional[float], job_option("element_size", "--element-size")),
    "layers": (Optional[int], job_option("layers", "--layers")),
    "blend": (Optional[bool], job_option("blend", "--blend/--no-blend")),
    "blend_angle": (Optional[float], job_option("blend_angle", "--blend-angle")),
    "simulate": (Optional[str], job_option("simulate", "--simulate")),
    "joint_load": (Optional[float], job_option("joint_load", "--joint-load")),
    "medial_offset": (Optional[float], job_option("medial_offset", "--medial-offset")),
    "quadriceps": (Optional[float], job_option("quadriceps", "--quadriceps")),
    "flexion": (Optional[float], job_option("flexion", "--flexion")),
    "activity": (Optional[str], job_option("activity", "--activity")),
    "peak_load": (Optional[float], job_option("peak_load", "--peak-load")),
    "fe_cartilage": (Optional[str], job_option("fe_cartilage", "--fe-cartilage")),
    "force": (Optional[bool], job_option("force", "--force/--no-force")),
}


def dataclass_flags(cls, skip: tuple[str, ...] = (), help: dict[str, str] | None = None,
                    names: dict[str, str] | None = None) -> dict:
    """Flags for the fields of a dataclass of options, with its defaults: name -> (type, flag).  A field's
    flag is ``--max-minutes`` for ``max_minutes`` unless ``names`` says otherwise; a tuple of ints is a
    comma-separated string."""
    flags = {}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        default = f.default
        kind = str if isinstance(default, tuple) else type(default)
        text = ",".join(map(str, default)) if isinstance(default, tuple) else default
        flag = (names or {}).get(f.name, "--" + f.name.replace("_", "-"))
        flags[f.name] = (kind, typer.Option(text, flag, help=(help or {}).get(f.name)))
    return flags


def with_flags(flags: dict, name: str):
    """Give a command ``flags`` (name -> (type, flag)) after its own parameters; they reach it as one
    dict, its parameter ``name``."""
    def decorate(command):
        sig = signature(command, eval_str=True)
        own = [p for p in sig.parameters.values() if p.name != name]
        extra = [Parameter(k, Parameter.KEYWORD_ONLY, default=flag, annotation=kind) for k, (kind, flag) in flags.items()]

        @functools.wraps(command)
        def wrapper(*args, **kwargs):
            return command(*args, **{name: {k: kwargs.pop(k) for k in flags}}, **kwargs)

        wrapper.__signature__ = sig.replace(parameters=own + extra)
        return wrapper

    return decorate


#: Give a command the shared :data:`MESH_FLAGS`; they reach it as one dict, ``mesh_flags``.
with_mesh_flags = with_flags(MESH_FLAGS, "mesh_flags")


def _version(value: bool):
    if value:
        out.print(f"kneemesh {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: Optional[bool] = typer.Option(None, "--version", callback=_version, is_eager=True, help="Print the version."),
):
    """KneeMesh: robust hexahedral knee models from MRI and label maps."""
