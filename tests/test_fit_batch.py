"""`diffavatar fit-batch` (issue #34): a manifest of scans fitted on Ray, resumable and isolated, gathered
in a summary. The Ray runs skip without ray; the "says how to install it" test and the manifest's checks
do not."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from torch_diffavatar.batch import BatchJob, fit_state, output_names, read_manifest
from torch_diffavatar.cli import main
from torch_diffavatar.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
FIT_OPTIONS = ["--iters", "1", "--spacing", "0.08", "--no-progress"]
GOOD = ("a", "b")


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """A folder with two tiny synthetic skirt scans (``a/scan.ply``, ``b/scan.ply``), a broken one
    (``broken.ply``), ``all.csv`` listing the three and ``good.jsonl`` the two good ones."""
    pytest.importorskip("ray")
    folder = tmp_path_factory.mktemp("scans")
    for seed, name in enumerate(GOOD, 1):
        argv = ["make-scan", "skirt", "--out", str(folder / name), "--seed", str(seed), "--spacing", "0.05"]
        assert main([*argv, "--garment-points", "3000", "--body-points", "3000"]) == 0
    (folder / "broken.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nend_header\n")
    (folder / "all.csv").write_text("scan,garment\na/scan.ply,skirt\nbroken.ply,skirt\nb/scan.ply,skirt\n")
    lines = [json.dumps({"scan": f"{n}/scan.ply", "garment": "skirt"}) for n in GOOD]
    (folder / "good.jsonl").write_text("\n".join(lines) + "\n")
    return folder


@pytest.fixture(scope="module")
def batch(scans):
    """(--out, exit status) of an uninterrupted `fit-batch` of ``all.csv`` on 2 workers."""
    out = scans / "batch"
    code = main(["fit-batch", str(scans / "all.csv"), "--out", str(out), "--workers", "2", *FIT_OPTIONS])
    return out, code


def _summary(out: Path) -> dict:
    return {row["name"]: row for row in json.loads((out / "summary.json").read_text())}


def test_a_broken_scan_is_an_error_row_and_the_others_complete(batch):
    out, code = batch
    rows = _summary(out)
    assert code == 1  # some scan failed
    assert [rows[n]["status"] for n in ("a-scan", "broken", "b-scan")] == ["ok", "error", "ok"]
    assert "broken.ply" in rows["broken"]["error"] and "\n" not in rows["broken"]["error"]
    for name in ("a-scan", "b-scan"):
        report = json.loads((out / name / "report.json").read_text())
        assert rows[name]["chamfer_final"] == report["chamfer_final"] and rows[name]["run"] == "fitted"
        assert not (out / name / "INCOMPLETE").exists()
    csv_lines = (out / "summary.csv").read_text().splitlines()
    assert csv_lines[0].startswith("name,scan,status") and len(csv_lines) == 4
    from PIL import Image

    with Image.open(out / "a-scan" / "before_after.png") as im:
        tile_h = round(im.height * 480 / im.width)
    with Image.open(out / "summary.png") as im:  # a 2-column grid of 3 tiles: 2 rows
        assert im.width == 2 * 480 and im.height == 2 * (tile_h + 18)
        assert im.getpixel((480 + 240, 18 + tile_h // 2)) == (235, 235, 235)  # the broken scan's: grey


def test_a_rerun_skips_finished_scans(batch, scans):
    out, _ = batch
    stamps = {n: (out / n / "report.json").stat().st_mtime_ns for n in ("a-scan", "b-scan")}
    before = _summary(out)
    code = main(["fit-batch", str(scans / "all.csv"), "--out", str(out), "--workers", "2", *FIT_OPTIONS])
    rows = _summary(out)
    assert code == 1 and rows["broken"]["status"] == "error"
    for name, stamp in stamps.items():
        assert rows[name]["run"] == "skipped" and (out / name / "report.json").stat().st_mtime_ns == stamp
        assert rows[name]["chamfer_final"] == before[name]["chamfer_final"]


def test_a_finished_scan_with_other_settings_is_an_error_not_skipped(batch, scans, tmp_path):
    """A folder that a batch fitted with ``--iters 1`` is not passed off as the result of ``--iters 2`` (or
    of an edited scan): its row is an error that names what changed, and the folder stays as it was."""
    reference, _ = batch
    out = tmp_path / "out"
    shutil.copytree(reference / "a-scan", out / "scan")  # alone in its manifest, the scan's folder is "scan"
    manifest = tmp_path / "a.csv"
    manifest.write_text(f"scan,garment\n{scans / 'a' / 'scan.ply'},skirt\n")
    stamp = (out / "scan" / "report.json").stat().st_mtime_ns
    assert main(["fit-batch", str(manifest), "--out", str(out), *FIT_OPTIONS]) == 0
    assert _summary(out)["scan"]["run"] == "skipped" and _summary(out)["scan"]["status"] == "ok"
    options = ["--iters", "2", *FIT_OPTIONS[2:]]
    assert main(["fit-batch", str(manifest), "--out", str(out), *options]) == 1
    row = _summary(out)["scan"]
    assert row["status"] == "error" and "other settings (iters)" in row["error"]
    assert (out / "scan" / "report.json").stat().st_mtime_ns == stamp


def test_a_killed_batch_reruns_to_the_uninterrupted_results(batch, scans):
    """One worker; SIGKILL to the driver once the first scan is done and the second has its set-up; a
    rerun skips the first, finishes the second, and each ends as in the uninterrupted batch."""
    reference, _ = batch
    out = scans / "killed"
    argv = [sys.executable, "-m", "torch_diffavatar.cli", "fit-batch", str(scans / "good.jsonl")]
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    proc = subprocess.Popen(
        [*argv, "--out", str(out), "--workers", "1", *FIT_OPTIONS],
        env=env,
        start_new_session=True,  # Ray's helpers join its group: removed with it at the end
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 120
        while not (out / "b-scan" / "setup.pt").exists() and time.monotonic() < deadline:
            assert proc.poll() is None, "the batch ended before it was killed"
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert fit_state(out / "a-scan") == "done" and (out / "b-scan" / "INCOMPLETE").exists()
        code = main(
            ["fit-batch", str(scans / "good.jsonl"), "--out", str(out), "--workers", "2", *FIT_OPTIONS]
        )
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    assert code == 0
    rows, expected = _summary(out), _summary(reference)
    assert rows["a-scan"]["run"] == "skipped"
    for name in ("a-scan", "b-scan"):
        assert rows[name]["status"] == "ok"
        for key in ("chamfer_initial", "chamfer_final"):
            assert rows[name][key] == expected[name][key], (name, key)
        assert (out / name / "pattern.json").read_text() == (reference / name / "pattern.json").read_text()


def test_without_ray_it_says_how_to_install(monkeypatch, tmp_path, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    (tmp_path / "m.csv").write_text("scan,garment\n")
    assert main(["fit-batch", str(tmp_path / "m.csv"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert 'pip install "torch_diffavatar[ray]"' in err and len(err.splitlines()) == 1


def test_manifest_rows_resolve_against_its_folder(tmp_path):
    for sub in ("x", "y"):
        (tmp_path / sub).mkdir()
        (tmp_path / sub / "scan.ply").write_text("ply\n")
    (tmp_path / "solo.ply").write_text("ply\n")
    (tmp_path / "m.jsonl").write_text(
        '{"scan": "x/scan.ply", "garment": "dress", "units": "cm", "up": "z"}\n\n'
        '{"scan": "y/scan.ply", "garment": "skirt", "body": "x"}\n{"scan": "solo.ply", "garment": "pants"}\n'
    )
    jobs = read_manifest(tmp_path / "m.jsonl")
    assert [j.name for j in jobs] == ["x-scan", "y-scan", "solo"]
    assert jobs[0].scan == str(tmp_path / "x" / "scan.ply") and (jobs[0].units, jobs[0].up) == ("cm", "z")
    assert jobs[1].body == str(tmp_path / "x") and jobs[1].config is None and jobs[2].garment == "pants"
    assert output_names(["/d/a/s/scan.ply", "/d/b/s/scan.ply", "/d/c.ply"]) == ["a-s-scan", "b-s-scan", "c"]
    assert output_names(["/x/a/b.ply", "/y/a-b.ply", "/y/b.ply"]) == ["a-b", "y-a-b", "y-b"]


@pytest.mark.parametrize(
    "text, suffix, message",
    [
        ("scan\nx.ply\n", ".csv", "no garment column"),
        ('{"scan": "x.ply", "garment": "skirt", "colour": 1}\n', ".jsonl", "unknown key colour"),
        ("scan,garment\nmissing.ply,skirt\n", ".csv", "scan missing.ply not found"),
        ("scan,garment\nx.ply,skirt\n./x.ply,dress\n", ".csv", "listed twice"),
        ("scan,garment\n", ".csv", "lists no scans"),
        ("scan,garment\nx.ply,\n", ".csv", "line 2: no garment"),
        ("[1]\n", ".jsonl", "not a JSON object"),
        ("scan,garment,units\nx.ply,skirt,inch\n", ".csv", "units 'inch' is not one of"),
    ],
)
def test_bad_manifests_are_one_line_errors(tmp_path, text, suffix, message):
    (tmp_path / "x.ply").write_text("ply\n")
    path = tmp_path / f"m{suffix}"
    path.write_text(text)
    with pytest.raises(InputError, match=message) as info:
        read_manifest(path)
    assert "\n" not in str(info.value)


def test_a_bad_manifest_through_the_command(tmp_path, capsys):
    pytest.importorskip("ray")
    (tmp_path / "x.ply").write_text("ply\n")
    (tmp_path / "m.csv").write_text("scan,garment,colour\nx.ply,skirt,red\n")
    assert main(["fit-batch", str(tmp_path / "m.csv"), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "line 2: unknown key colour" in err and len(err.strip().splitlines()) == 1


def test_each_task_fits_with_one_thread_and_resumes_a_half_done_folder(tmp_path, monkeypatch):
    """`fit_one` (the Ray task, called here directly): `fit_command`'s arguments, one torch thread,
    ``--resume`` for a folder a fit started, and an unexpected error as the row's one line."""
    import torch

    import torch_diffavatar.commands.fit as fit
    from torch_diffavatar.commands.fit_batch import fit_one

    seen = []

    def fake_fit(args):
        seen.append((torch.get_num_threads(), args))
        if args.garment == "boom":
            raise RuntimeError("went\nwrong")
        Path(args.out).mkdir(exist_ok=True)  # a fit writes its folder (and the batch its record there)
        return {"chamfer_initial": 0.02, "chamfer_final": 0.01, "warnings": ["w"]}

    monkeypatch.setattr(fit, "fit_command", fake_fit)
    previous = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        job = BatchJob(scan=str(tmp_path / "s.ply"), garment="skirt", name="s", units="cm")
        row = fit_one(job.to_dict(), str(tmp_path), 3, 0.05)
        (tmp_path / "s" / "setup.pt").write_text("")
        resumed = fit_one(job.to_dict(), str(tmp_path), 3, 0.05)
        failed = fit_one({**job.to_dict(), "garment": "boom", "name": "t"}, str(tmp_path), 3, 0.05)
    finally:
        torch.set_num_threads(previous)
    (threads, args), (_, args2) = seen[0], seen[1]
    assert threads == 1 and args.out == str(tmp_path / "s") and (args.iters, args.spacing) == (3, 0.05)
    assert args.units == "cm" and args.json and not args.resume and args2.resume
    assert (row["status"], row["run"], row["chamfer_final"], row["warnings"]) == ("ok", "fitted", 0.01, ["w"])
    assert (
        resumed["run"] == "resumed" and json.loads((tmp_path / "s" / "batch.json").read_text())["iters"] == 3
    )
    assert failed["status"] == "error" and failed["error"] == "RuntimeError: went wrong"


def test_the_benchmark_compares_each_scans_chamfer(tmp_path):
    """scripts/bench_fit_batch.py's check that the loop and the batches fitted the same: per scan folder."""
    from helpers_scripts import load_script

    bench = load_script("bench_fit_batch")
    for name, chamfer in (("s1-scan", 0.01), ("s2", 0.02)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "report.json").write_text(json.dumps({"chamfer_final": chamfer}))
    assert bench.chamfers(tmp_path) == {"s1": 0.01, "s2": 0.02}
