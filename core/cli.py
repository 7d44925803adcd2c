"""The ``inspect`` command line."""
from __future__ import annotations

import os
import sys

import click

from core.commands import (bench, depth, depth_suite, hardware, inspection, masters, repeatability, sim, stereo,
                           view)
from core.interrupts import raise_if_interrupted

BUILTIN_COMMAND_MODULES = (inspection, bench, stereo, depth, depth_suite, repeatability, hardware, masters, sim, view)


@click.group()
@click.version_option(package_name="stereo-inspect")
def cli() -> None:
    """stereo-inspect: stereo surface inspection of metal parts."""


@cli.group("eval")
def eval_group() -> None:
    """Evaluate a stereo backend, depth or a detector on a benchmark."""


@cli.group("train")
def train_group() -> None:
    """Train models."""


@cli.group("data")
def data_group() -> None:
    """Prepare data sets."""


@cli.group("camera")
def camera_group() -> None:
    """Work with cameras."""


def _build() -> click.Group:
    for module in BUILTIN_COMMAND_MODULES:
        module.register(cli)
    from core.registry import default_registry

    registry = default_registry()
    for impl in registry.manager.hook.stereo_inspect_commands.get_hookimpls():
        try:
            impl.function(cli=cli)
        except Exception as exc:  # one package's broken commands must not take the others with them
            registry.failed.append(f"{impl.plugin_name} (its commands): {type(exc).__name__}: {exc}")
    return cli


def quiet_opencv() -> None:
    """OpenCV's own warnings off (its errors stay), unless OPENCV_LOG_LEVEL asks otherwise: a file it cannot
    decode is reported in one line naming it, which its warning about the same file would precede."""
    import cv2

    if "OPENCV_LOG_LEVEL" not in os.environ:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def main(args: list[str] | None = None) -> None:
    """The ``inspect`` console script, on ``args`` (default: the command line)."""
    from core import kernel_cache
    from core.memory import keep_freed_memory

    said = kernel_cache.ensure()  # before any kernel's module is imported
    if said is not None:
        click.echo(said, err=True)
    keep_freed_memory()  # before the first frame's volumes are allocated
    quiet_opencv()
    try:
        sys.exit(_build().main(args, prog_name="inspect", standalone_mode=True))
    except BrokenPipeError:  # the reader of the output went away (`| head`): nothing left to tell
        sys.exit(1)
    except RuntimeError as exc:
        if "cannot cache function" not in str(exc):
            raise
        # not even the temporary folder could be written (kernel_cache.ensure)
        click.echo(f"Error: numba can keep the compiled kernels nowhere ({exc}): set NUMBA_CACHE_DIR to a folder "
                   f"this user can write", err=True)
        sys.exit(2)
    except SystemError as exc:
        try:
            raise_if_interrupted(exc)
        except KeyboardInterrupt:  # Ctrl-C inside a compiled kernel: what click says of any other Ctrl-C
            click.echo("Aborted!", err=True)
            sys.exit(1)
        raise
    except OSError as exc:
        # a path the system refuses (a name too long, a folder without permission) that no command checked
        # first: one line naming it, as for any other bad input, not a traceback
        where = f"{exc.filename}: " if exc.filename else ""
        click.echo(f"error: {where}{exc.strerror or exc}", err=True)
        sys.exit(2)
