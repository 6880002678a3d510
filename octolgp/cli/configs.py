"""The map configuration of a command: ``--config FILE.toml``, then the explicit flags.

Every command that builds a map (``run``, ``replay``, ``build``, ``eval``) and ``dump-config``
resolve their :class:`~octolgp.config.MapConfig` through :func:`resolve_config`: the file's
values (or the defaults), then each mapping flag the user gave, then the data's dimension. The
resolved config is written beside the output with :func:`write_config`.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from octolgp.config import MapConfig
from octolgp.errors import OctolgpError

__all__ = [
    "add_config_option",
    "add_dump_config",
    "check_config_output",
    "check_outputs",
    "cmd_dump_config",
    "config_path",
    "resolve_config",
    "write_config",
]


def add_config_option(p: argparse.ArgumentParser) -> None:
    """``--config FILE.toml``: the map configuration; explicit flags override it."""
    p.add_argument(
        "--config",
        metavar="FILE.toml",
        default=None,
        help="map configuration (sections as MapConfig's: [online], [training], ...; see "
        "octolgp dump-config); explicit flags override it",
    )
    p.add_argument(
        "--free-range",
        type=_free_range,
        default=None,
        metavar="M",
        help="metres from the sensor a beam's evidence reaches (training.free_range, as "
        "OctoMap's maxrange: no-returns free up to it, returns beyond it without their "
        "hit; default inf: whole beams)",
    )


def _free_range(text: str) -> float:
    """``--free-range``: metres > 0, or ``inf``."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a number of metres > 0 or inf, got {text}")
    return value


def resolve_config(
    args: argparse.Namespace, dim: int | None = None, *, n_jobs: int | None = None
) -> MapConfig:
    """The map configuration a command asks for, resolved (:meth:`MapConfig.resolve`).

    Parameters
    ----------
    args : argparse.Namespace
        Read: ``config`` (a TOML file, else the defaults), then the flags given (not
        ``None``): ``resolution`` (metres), ``free_range`` (metres,
        ``training.free_range``), ``learn_scans`` (``online.learn_scans``) and
        ``memory_budget`` (MB, ``memory_budget_mb``); absent attributes are skipped.
    dim : int, optional
        The data's dimension, 2 or 3; it replaces the file's ``dim``.
    n_jobs : int, optional
        ``online.n_jobs`` (leaf-fitting threads), where the command's ``--jobs`` means that.

    Raises
    ------
    OctolgpError
        On a missing or invalid file, an unknown key or a bad value (naming the file and the
        key), or a flag the config refuses.
    """
    path = getattr(args, "config", None)
    base = MapConfig() if path is None else MapConfig.from_toml(path)
    changes: dict[str, Any] = {}
    if dim is not None:
        changes["dim"] = dim
    if getattr(args, "resolution", None) is not None:
        changes["resolution"] = args.resolution
    if getattr(args, "memory_budget", None) is not None:
        changes["memory_budget_mb"] = args.memory_budget
    if getattr(args, "free_range", None) is not None:
        changes["training"] = dataclasses.replace(base.training, free_range=args.free_range)
    online: dict[str, Any] = {}
    if getattr(args, "learn_scans", None) is not None:
        online["learn_scans"] = args.learn_scans
    if n_jobs is not None:
        online["n_jobs"] = n_jobs
    if online:
        changes["online"] = dataclasses.replace(base.online, **online)
    return (dataclasses.replace(base, **changes) if changes else base).resolve()


def check_outputs(overwrite: bool, *paths: Path, what: str = "--out") -> None:
    """Refuse outputs that exist already unless ``--overwrite`` was given.

    ``what`` names the outputs in the message (the option, or what the file is).

    Raises
    ------
    OctolgpError
        Naming the first existing path.
    """
    for p in paths:  # one iteration per file the command writes
        if p.exists() and not overwrite:
            raise OctolgpError(f"{what} {str(p)!r} already exists (pass --overwrite to replace it)")


def check_config_output(
    overwrite: bool, target: Path, given: str | None, config: MapConfig
) -> None:
    """Refuse, before any work, what :func:`write_config` would refuse or overwrite.

    An existing ``target`` is refused unless ``--overwrite``, but for the ``--config`` file
    itself (``given``), which is kept when it reads back to ``config`` and refused
    otherwise.

    Raises
    ------
    OctolgpError
        Naming ``target``.
    """
    if given is not None and _is_given(target, given):
        if MapConfig.from_toml(given) != config:
            raise OctolgpError(
                f"the resolved config would overwrite --config {given!r}: choose another --out"
            )
        return
    check_outputs(overwrite, target, what="the resolved config")


def _is_given(target: Path, given: str) -> bool:
    """Whether ``target`` is the ``--config`` file ``given``."""
    return target.exists() and target.resolve() == Path(given).resolve()


def config_path(out: str | Path, folder: bool = False) -> Path:
    """Where the resolved config of ``--out`` goes.

    ``FOLDER/config.toml`` for a results folder (``eval``); beside a map file, the map's file
    name with ``.toml`` added (``intel.octolgp`` -> ``intel.octolgp.toml``), so maps sharing a
    folder keep their own and a user's ``intel.toml`` is not the map's.
    """
    p = Path(out)
    return p / "config.toml" if folder else p.with_name(p.name + ".toml")


def write_config(config: MapConfig, target: Path, given: str | None = None) -> Path:
    """Write ``config`` as TOML to ``target``; returns ``target``.

    ``given`` is the ``--config`` file: when ``target`` is that file, it is left as it is if
    it reads back to ``config``, and refused otherwise (the user's file is never rewritten).

    The file is written through a temporary file and a rename
    (:func:`~octolgp.export.common.replacing`): never half a file.

    Raises
    ------
    OctolgpError
        If ``target`` is the ``--config`` file and the flags changed the config, or
        ``target`` cannot be written.
    """
    from octolgp.export.common import write_bytes

    if given is not None and _is_given(target, given):
        check_config_output(False, target, given, config)  # kept as it is, or refused
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    write_bytes(target, [config.to_toml().encode("utf-8")])
    return target


def add_dump_config(sub: Any, positive_int: Any, positive_float: Any) -> None:
    """The ``dump-config`` subparser (``sub``: the subparsers action)."""
    dump = sub.add_parser(
        "dump-config",
        help="print the resolved map configuration as TOML",
        description="Print the map configuration that --config FILE.toml and the mapping "
        "flags give, with every default filled in, as TOML (a starting point for --config).",
    )
    add_config_option(dump)
    dump.add_argument("--dim", type=int, choices=[2, 3], default=None, help="2 or 3")
    dump.add_argument("--resolution", type=positive_float, default=None, help="metres")
    dump.add_argument("--jobs", type=positive_int, default=None, help="online.n_jobs")
    dump.add_argument("--learn-scans", type=positive_int, default=None, help="online.learn_scans")
    dump.add_argument(
        "--memory-budget", type=positive_float, default=None, metavar="MB", help="RAM for leaves"
    )
    dump.set_defaults(func=cmd_dump_config)


def cmd_dump_config(args: argparse.Namespace) -> int:
    """``octolgp dump-config``: print the resolved config as TOML."""
    print(resolve_config(args, args.dim, n_jobs=args.jobs).to_toml(), end="")
    return 0
