"""Batch fitting's plain parts (no Ray here): the manifest (`read_manifest`), which scans a batch still has to
fit (`fit_state`), and the results gathered (`write_summary`, `summary_picture`).

A manifest is a CSV with a header, or JSON lines, with the keys of `MANIFEST_KEYS` (``scan`` and ``garment``
required); relative paths resolve against the manifest's folder. Each scan gets one asset folder under the
batch's ``--out``, named after its file (`output_names`).
"""

from __future__ import annotations

import csv
import hashlib
import io
from dataclasses import asdict, dataclass
from pathlib import Path

from torch_diffavatar.atomic_file import atomic_write_text
from torch_diffavatar.errors import InputError, parse_json, read_json_file
from torch_diffavatar.fit_scan import INCOMPLETE
from torch_diffavatar.json_io import dumps_json

MANIFEST_KEYS = ("scan", "garment", "config", "units", "up", "body")
REQUIRED_KEYS = ("scan", "garment")
SUMMARY_CSV, SUMMARY_JSON, SUMMARY_PNG = "summary.csv", "summary.json", "summary.png"
BATCH_RECORD = "batch.json"  # in a scan's folder: the batch settings it was fitted with (`batch_settings`)
SUMMARY_FIELDS = (
    "name",
    "scan",
    "status",
    "run",
    "seconds",
    "chamfer_initial",
    "chamfer_final",
    "warnings",
    "error",
)


@dataclass(frozen=True)
class BatchJob:
    """One manifest row: the scan (an absolute path), what `diffavatar fit` takes for it (None: its
    default) and ``name``, its asset folder under the batch's ``--out``."""

    scan: str
    garment: str
    name: str = ""
    config: str | None = None
    units: str | None = None
    up: str | None = None
    body: str | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def _rows(path: Path) -> list[tuple[int, dict]]:
    """(line number, row) of a CSV with a header or of JSON lines (``.jsonl``/``.json``/``.ndjson``)."""
    text = path.read_text()
    if path.suffix.lower() in (".jsonl", ".json", ".ndjson"):
        rows = []
        for k, line in enumerate(text.splitlines(), 1):
            if not line.strip():
                continue
            row = parse_json(line, f"manifest {path}, line {k}")
            if not isinstance(row, dict):
                raise InputError(f"manifest {path}, line {k}: not a JSON object")
            rows.append((k, row))
        return rows
    reader = csv.DictReader(io.StringIO(text))
    header = [h.strip() for h in reader.fieldnames or []]
    missing = [k for k in REQUIRED_KEYS if k not in header]
    if missing:
        raise InputError(f"manifest {path}: no {', '.join(missing)} column (header: {','.join(header)})")
    return [
        (k, {(key or "").strip(): (v or "").strip() for key, v in row.items()})
        for k, row in enumerate(reader, 2)
    ]


def _job(row: dict, where: str, folder: Path) -> BatchJob:
    """The `BatchJob` of one manifest ``row`` (at ``where``); paths resolved against ``folder``."""
    unknown = sorted(set(row) - set(MANIFEST_KEYS))
    if unknown:
        raise InputError(f"{where}: unknown key {', '.join(unknown)} (known: {', '.join(MANIFEST_KEYS)})")
    values = {k: (str(v).strip() if v is not None else "") for k, v in row.items()}
    for key in REQUIRED_KEYS:
        if not values.get(key):
            raise InputError(f"{where}: no {key}")

    def resolve(value: str) -> str:
        return str((folder / value).resolve())

    scan = resolve(values["scan"])
    if not Path(scan).is_file():
        raise InputError(f"{where}: scan {values['scan']} not found ({scan})")
    from torch_diffavatar.scan import UNITS, UP_AXES

    for key, known in (("units", UNITS), ("up", UP_AXES)):
        if values.get(key) and values[key] not in known:
            raise InputError(f"{where}: {key} {values[key]!r} is not one of {', '.join(known)}")
    garment = values["garment"]
    if (folder / garment).is_file():  # a pattern file beside the manifest; else a template's name
        garment = resolve(garment)
    return BatchJob(
        scan=scan,
        garment=garment,
        config=resolve(values["config"]) if values.get("config") else None,
        units=values.get("units") or None,
        up=values.get("up") or None,
        body=resolve(values["body"]) if values.get("body") else None,
    )


def output_names(scans: list[str]) -> list[str]:
    """One folder name per scan path: its file stem, with as many of its parent folders before it (joined
    by ``-``) as make it unique (``a/scan.ply``, ``b/scan.ply``, ``c.ply`` -> ``a-scan``, ``b-scan``, ``c``).

    Raises:
        InputError: a scan is listed twice (its folder name cannot be unique).
    """
    parts = [Path(s).with_suffix("").parts for s in scans]
    seen: dict[str, int] = {}
    for k, s in enumerate(scans):
        if s in seen:
            raise InputError(
                f"manifest: scan {s} is listed twice (rows {seen[s] + 1} and {k + 1}); "
                "its asset folders would have the same name"
            )
        seen[s] = k

    def name(p: tuple, depth: int) -> str:
        return "-".join(p[-depth:]).lstrip("-/") or "scan"

    def own_depth(k: int) -> int:  # the fewest trailing parts that no other scan's path ends with
        depth = 1
        while any(j != k and parts[j][-depth:] == parts[k][-depth:] for j in range(len(parts))):
            depth += 1
        return depth

    names = [name(p, own_depth(k)) for k, p in enumerate(parts)]
    depth = 1
    while len(set(names)) < len(names):  # "a/b.ply" and "a-b.ply": the same depth for all, deeper
        names = [name(p, depth) for p in parts]
        depth += 1
    return names


def read_manifest(path) -> list[BatchJob]:
    """The jobs of the manifest file ``path`` (see the module docstring), in its order, each named.

    Raises:
        InputError: no such file, no rows, a missing column, an unknown key, a scan file not there, or a
            scan listed twice.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"manifest {path} not found")
    jobs = [_job(row, f"manifest {path}, line {k}", path.parent.resolve()) for k, row in _rows(path)]
    if not jobs:
        raise InputError(f"manifest {path} lists no scans")
    names = output_names([j.scan for j in jobs])
    return [BatchJob(**{**j.to_dict(), "name": n}) for j, n in zip(jobs, names)]


def fit_state(folder: Path) -> str:
    """``"done"`` (its report is there and the fit finished writing: no `INCOMPLETE` marker), ``"partial"``
    (a fit started there) or ``"new"``, for a scan's asset ``folder``."""
    if (folder / "report.json").is_file() and not (folder / INCOMPLETE).exists():
        return "done"
    if folder.is_dir() and any(folder.iterdir()):
        return "partial"
    return "new"


def batch_settings(job: BatchJob, iters: int | None, spacing: float | None) -> dict:
    """What a batch fits ``job``'s folder with: its manifest row (the scan, config and body files also by
    content, SHA-256) and the batch's ``--iters`` / ``--spacing``, as plain data (`BATCH_RECORD`)."""
    row = {k: v for k, v in job.to_dict().items() if k != "name"}
    digests = {}
    for key in ("scan", "config", "body"):
        path = row.get(key)
        if path and Path(path).is_file():
            digests[key] = hashlib.sha256(Path(path).read_bytes()).hexdigest()
    return {"row": row, "sha256": digests, "iters": iters, "spacing": spacing}


def record_settings(folder: Path, settings: dict) -> None:
    """Write ``settings`` (`batch_settings`) into the finished ``folder``'s `BATCH_RECORD`."""
    atomic_write_text(folder / BATCH_RECORD, dumps_json(settings, indent=1) + "\n")


def changed_settings(folder: Path, settings: dict) -> list[str]:
    """What differs between ``settings`` and those the finished ``folder`` was fitted with by a batch
    (``iters``, ``spacing``, ``scan``, ``config``, ...; sorted); [] when they agree or when no batch recorded
    them (a folder fitted otherwise is taken as it is)."""
    path = folder / BATCH_RECORD
    if not path.is_file():
        return []
    try:
        old = read_json_file(path, f"{path}: missing")
    except InputError:
        return ["batch.json unreadable"]

    def flat(d: dict) -> dict:
        return {
            **d.get("row", {}),
            **{f"{k} contents": v for k, v in d.get("sha256", {}).items()},
            "iters": d.get("iters"),
            "spacing": d.get("spacing"),
        }

    a, b = flat(old), flat(settings)
    return sorted(k for k in {**a, **b} if a.get(k) != b.get(k))


def result_row(job: BatchJob, run: str, seconds: float, report: dict | None, error: str | None) -> dict:
    """A summary row (`SUMMARY_FIELDS`) of ``job``: ``run`` is ``fitted``, ``resumed`` or ``skipped``;
    ``report``: its ``report.json`` (None when it failed); ``error``: the failure's one line."""
    report = report or {}
    return {
        "name": job.name,
        "scan": job.scan,
        "status": "error" if error is not None else "ok",
        "run": run,
        "seconds": round(float(seconds), 2),
        "chamfer_initial": report.get("chamfer_initial"),
        "chamfer_final": report.get("chamfer_final"),
        "warnings": list(report.get("warnings", [])),
        "error": error,
    }


def write_summary(out: Path, rows: list[dict]) -> None:
    """``out/summary.json`` (a list of the rows) and ``out/summary.csv`` (warnings joined by `` | ``), each
    written whole or not at all."""
    atomic_write_text(out / SUMMARY_JSON, dumps_json(rows, indent=1) + "\n")
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=SUMMARY_FIELDS, lineterminator="\n")
    writer.writeheader()
    for row in rows:
        flat = {k: ("" if row.get(k) is None else row[k]) for k in SUMMARY_FIELDS}
        flat["warnings"] = " | ".join(row.get("warnings") or [])
        writer.writerow(flat)
    atomic_write_text(out / SUMMARY_CSV, buf.getvalue())


def summary_picture(out: Path, rows: list[dict], *, tile_width: int = 480, columns: int = 2) -> Path:
    """``out/summary.png``: a grid of each scan's before/after picture (``NAME/before_after.png``, rendered
    by `render` when the fit wrote its assets), scaled to ``tile_width`` pixels wide (the tiles as high as
    the highest; a quarter of the width without any picture), its name, status and Chamfer before -> after
    above it; a failed scan's tile is grey with its error."""
    import numpy as np
    from PIL import Image, ImageDraw

    from torch_diffavatar.render import save_png

    pictures = {}
    for row in rows:
        path = out / row["name"] / "before_after.png"
        if row["status"] == "ok" and path.is_file():
            with Image.open(path) as im:
                im = im.convert("RGB")
            pictures[row["name"]] = im.resize((tile_width, max(1, round(im.height * tile_width / im.width))))
    label_h = 18
    tile_h = max((im.height for im in pictures.values()), default=tile_width // 4)
    tiles = []
    for row in rows:
        tile = Image.new("RGB", (tile_width, tile_h + label_h), (235, 235, 235))
        if row["name"] in pictures:
            tile.paste(pictures[row["name"]], (0, label_h))
        text = f"{row['name']}: {row['status']}"
        if row["status"] == "ok" and row.get("chamfer_final") is not None:
            text += f", Chamfer {1e3 * row['chamfer_initial']:.1f} -> {1e3 * row['chamfer_final']:.1f} mm"
        else:
            text += f" ({row.get('error')})"
        ImageDraw.Draw(tile).text((4, 3), text[:90], fill=(0, 0, 0) if row["status"] == "ok" else (170, 0, 0))
        tiles.append(tile)
    columns = max(1, min(columns, len(tiles)))
    grid_rows = max(1, -(-len(tiles) // columns))
    sheet = Image.new("RGB", (columns * tile_width, grid_rows * (tile_h + label_h)), (255, 255, 255))
    for k, tile in enumerate(tiles):
        sheet.paste(tile, ((k % columns) * tile_width, (k // columns) * (tile_h + label_h)))
    return save_png(np.asarray(sheet, dtype=np.uint8), out / SUMMARY_PNG)
