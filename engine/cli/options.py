"""Options several commands share: the scene argument, the Dask cluster options, the
``--radar`` option; and :func:`input_errors`, where an engine call reports bad input
with a plain ``ValueError``."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ..errors import IsacTwinError, UsageError
from ..scaleout.checkpoint import checkpoint_dir
from ..scaleout.cluster import check_cluster_args, cluster_client, trace_grid_tiled
from ..scene.bundled import bundled_scene_dir
from ..scene.config import load_config

__all__ = ["scene_arg", "scene_path", "cluster_args", "check_cluster_options",
           "uses_cluster", "tiled_tracer", "radar_arg", "radar_kw", "check_radar",
           "input_errors"]


@contextmanager
def input_errors(prefix: str = "", types: tuple[type[Exception], ...] = (ValueError,)
                 ) -> Iterator[None]:
    """Turn the plain ``ValueError`` of an engine call that validates what the user gave
    into a :class:`~isac_twin.errors.UsageError` (``main`` prints it as one line, exit 2).

    Errors of the engine's own hierarchy pass unchanged. Each use marks an engine call
    whose bad-input error is not yet typed.

    Args:
        prefix: put before the message, e.g. ``"--csi-snr: "`` (the option it came from).
        types: the exception types turned into a ``UsageError``.
    """
    try:
        yield
    except IsacTwinError:
        raise
    except types as exc:
        raise UsageError(f"{prefix}{exc}") from exc


def scene_arg(p: argparse.ArgumentParser) -> None:
    """The optional positional scene folder (or its twin.toml)."""
    p.add_argument("scene", nargs="?", type=Path, default=None,
                   help="scene folder or its twin.toml (default: the bundled aces_lab)")


def scene_path(args: argparse.Namespace) -> Path:
    """The scene the user named, else the bundled lab."""
    return args.scene if args.scene is not None else bundled_scene_dir()


def cluster_args(p: argparse.ArgumentParser) -> None:
    """``--workers``, ``--scheduler``, ``--tile-size``: trace on a Dask cluster."""
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="trace tiles on a local Dask cluster of N single-threaded worker "
                        "processes (see docs/scaleout.md)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS",
                   help="trace tiles on a running Dask cluster (e.g. tcp://host:8786); the "
                        "scene folder must be at the same path on every worker")
    p.add_argument("--tile-size", type=int, default=None,
                   help="free points per tile (--workers/--scheduler; a multiple of the "
                        "1024-point chunk, default one chunk)")


def uses_cluster(args: argparse.Namespace) -> bool:
    """Whether ``--workers`` or ``--scheduler`` asks for a cluster."""
    return args.workers is not None or args.scheduler is not None


def check_cluster_options(args: argparse.Namespace) -> None:
    """Refuse bad ``--workers``/``--scheduler``/``--tile-size`` before any work.

    Raises:
        UsageError: naming the option and what was expected.
    """
    with input_errors():
        check_cluster_args(args.workers, args.scheduler)
    if args.tile_size is not None and args.tile_size < 1:
        raise UsageError(f"--tile-size {args.tile_size}: expected at least 1 point per tile")
    if args.tile_size is not None and not uses_cluster(args):
        raise UsageError("--tile-size: only with --workers or --scheduler")


def tiled_tracer(args: argparse.Namespace, output: Path):
    """``trace_grid``'s stand-in that traces on the cluster of ``--workers`` /
    ``--scheduler`` (started, or connected to, only when a grid is traced), with its
    tile checkpoints beside ``output`` (the grid or database file)."""
    checkpoints = checkpoint_dir(output)

    def trace(*a, **kw):
        with cluster_client(args.workers, args.scheduler) as client:
            return trace_grid_tiled(*a, client=client, checkpoints=checkpoints,
                                    tile_size=args.tile_size, **kw)

    return trace


def radar_arg(p: argparse.ArgumentParser) -> None:
    """``--radar``: where the [[sensing]] radar computes its frames."""
    p.add_argument("--radar", choices=("auto", "thread", "process", "sync"), default="auto",
                   help="where the [[sensing]] radar computes its frames: a worker thread, "
                        "a child process (the twin's steps do not wait behind a frame), "
                        "or the stepping thread (each frame on its own step); auto "
                        "(default): process with --rate, thread otherwise")


def radar_kw(args: argparse.Namespace) -> dict:
    """The Twin keywords of ``--radar`` (and ``--rate``)."""
    radar = args.radar if args.radar != "auto" else ("process" if args.rate else "thread")
    return {"sync_sensing": radar == "sync", "sensing_process": radar == "process"}


def check_radar(args: argparse.Namespace) -> None:
    """``--radar`` named for a scene without a radar is refused, not ignored; read from
    the config, before a twin is built.

    Raises:
        UsageError: the scene has no [[sensing]] radar.
    """
    if args.radar == "auto":
        return
    cfg = load_config(scene_path(args))
    if not cfg.sensing:
        raise UsageError(f"--radar {args.radar}: {cfg.path} has no [[sensing]] radar")
