"""The `diffavatar` command: each module of `torch_diffavatar.commands` registers its sub-commands."""

from __future__ import annotations

import argparse
import errno
import importlib
import re
import sys

from torch_diffavatar.errors import InputError, NonFiniteError, SimulationError
from torch_diffavatar.json_io import dumps_json

# Each module defines `register(subparsers)`; its sub-commands set `func(args) -> int | dict`.
_COMMAND_MODULES = tuple(
    f"torch_diffavatar.commands.{name}"
    for name in ("mesh", "drape", "body", "fit", "fit_batch", "demo", "animate", "make_scan", "eval")
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="diffavatar",
        description="Simulation-ready avatars (body, sewing pattern, material) from a scan.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for name in _COMMAND_MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name != name:  # a real import error inside the module, not a missing area
                raise
            continue
        module.register(sub)
    return parser


def emit_json(obj) -> None:
    """Print one JSON object on one line (the CLI contract for `--json`).

    Raises:
        ValueError: ``obj`` holds a non-finite number (`json_io.dumps_json`); nothing is printed.
    """
    print(dumps_json(obj, sort_keys=False))


# options whose values may start with "-" (``--up -y``), which argparse would take for an option
_SIGNED_VALUE_OPTIONS = ("--up", "--scan-up")


def _join_signed_values(argv: list[str]) -> list[str]:
    """``["--up", "-y"]`` -> ``["--up=-y"]`` for the `_SIGNED_VALUE_OPTIONS`."""
    out: list[str] = []
    k = 0
    while k < len(argv):
        if argv[k] in _SIGNED_VALUE_OPTIONS and k + 1 < len(argv) and argv[k + 1].startswith("-"):
            out.append(f"{argv[k]}={argv[k + 1]}")
            k += 2
        else:
            out.append(argv[k])
            k += 1
    return out


def _os_error_line(exc: OSError) -> str:
    """One line for an `OSError`: what failed and on which path, with the remedy for the common ones."""
    if exc.strerror is None:
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    where = f": {exc.filename}" if exc.filename else ""
    hint = {
        errno.ENOSPC: " (free some space, or choose another --out)",
        errno.ENOTDIR: " (a part of this path is a file, not a folder)",
        errno.EEXIST: " (a file is in the way of a folder)",
        errno.EACCES: " (not writable: choose another --out)",
        errno.EROFS: " (a read-only file system: choose another --out)",
    }.get(exc.errno, "")
    return f"{exc.strerror}{where}{hint}"


def _one_line(text: str) -> str:
    """``text`` on one line: a message that quotes a library's error (YAML marks its place on three lines)
    must not break the CLI's one-line contract."""
    return " ".join(part.strip() for part in text.splitlines() if part.strip())


# how a command's interrupted work continues (its checkpoints)
RESUME_HINTS = {
    "fit": "--resume continues from the last checkpoint",
    "fit-batch": "the same command again continues where it stopped",
}


def _error(command: str, message: str) -> int:
    """Print ``message`` as the command's one error line on stderr; returns the exit status, 2."""
    print(f"diffavatar {command}: error: {_one_line(message)}", file=sys.stderr)
    return 2


# what a failed allocation says: numpy and Python raise MemoryError, torch a RuntimeError with this
_NO_MEMORY = "can't allocate memory"


def _memory_error_line(exc: BaseException) -> str:
    """One line for a failed allocation: how much was asked, when the error says, and what needs less."""
    size = re.search(r"allocate (\d+) bytes|allocate ([\d.]+ [KMGT]i?B)", str(exc))
    asked = "" if size is None else size[2] or f"{int(size[1]) / 2**30:.3g} GiB"
    return (
        f"out of memory{f' ({asked} asked)' if asked else ''}: the input is too big for this machine; a "
        "smaller scan (fit-body, segment: --max-points) or pattern, or a coarser --spacing, needs less"
    )


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(_join_signed_values(sys.argv[1:] if argv is None else list(argv)))
    try:
        result = args.func(args)
    except (InputError, SimulationError, NonFiniteError) as exc:  # NaN in a result: no file written with it
        return _error(args.command, str(exc))
    except OSError as exc:  # a path or the disk (not found, a file where a folder goes, full, read-only)
        return _error(args.command, _os_error_line(exc))
    except MemoryError as exc:
        return _error(args.command, _memory_error_line(exc))
    except RuntimeError as exc:
        if _NO_MEMORY not in str(exc):  # any other RuntimeError is a bug: its traceback is wanted
            raise
        return _error(args.command, _memory_error_line(exc))
    except KeyboardInterrupt:  # Ctrl-C: one line, and the shell's status for SIGINT (128 + 2)
        hint = f"; {RESUME_HINTS[args.command]}" if args.command in RESUME_HINTS else ""
        print(f"diffavatar {args.command}: interrupted{hint}", file=sys.stderr)
        return 130
    if isinstance(result, dict):
        if getattr(args, "json", False):
            try:
                emit_json(result)
            except ValueError as exc:  # NaN or inf: refused rather than printed as non-JSON
                return _error(args.command, str(exc))
        return 0
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
