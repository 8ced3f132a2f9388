"""Bad input, as a careless or hostile user gives it (issue #33): every case runs through the CLI entry point
and must end with exit 2, one line on stderr naming what is wrong, no traceback, and nothing left behind
that looks like a finished output. Every case is refused before any heavy work (body fit, drape), so the
suite stays fast; what needs a body fit to show (a body fit far from the scan) is tested by its function.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from torch_diffavatar import cli, scan
from torch_diffavatar.fit_checkpoint import SETUP, atomic_save
from torch_diffavatar.fit_config import RESOLVED_CONFIG, load_config
from torch_diffavatar.fit_scan import INCOMPLETE, body_fit_warnings, fit_fingerprint
from torch_diffavatar.pattern import load_template, save_pattern
from torch_diffavatar.pattern.garmentcode import MAX_PANELS, pattern_to_dict
from torch_diffavatar.scan import load_scan, save_ply
from torch_diffavatar.scan_intake import intake_scan

DEMO_SCAN = Path(__file__).resolve().parents[1] / "torch_diffavatar" / "data" / "demo_scan.ply"


@pytest.fixture(scope="module")
def person() -> np.ndarray:
    """(N, 3) [m] points of a clothed person standing on y = 0 (the bundled demo scan)."""
    return load_scan(DEMO_SCAN, check=False).points


def _refused(argv: list[str], capsys, *must_say: str, progress: bool = False) -> str:
    """Run the CLI; assert exit 2 and one error line on stderr, saying each of ``must_say``: the only line
    there, or (``progress``: refused after the intake) the last one, after the intake's own lines."""
    code = cli.main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert lines[-1].startswith(f"diffavatar {argv[0]}: error: "), err
    assert len(lines) == 1 or (progress and not any("error" in line for line in lines[:-1])), err
    for words in must_say:
        assert words in lines[-1], err
    return lines[-1]


def _write(path: Path, data: str | bytes) -> Path:
    if isinstance(data, bytes):
        path.write_bytes(data)
    else:
        path.write_text(data)
    return path


def _sphere(count: int = 20000, radius: float = 0.8) -> np.ndarray:
    points = np.random.default_rng(0).normal(size=(count, 3))
    return radius * points / np.linalg.norm(points, axis=1, keepdims=True)


# -- scans: each refused by the intake, before the body fit; fit-body's --out is never made -------------

SCAN_CASES = {
    "missing": (None, [], "file not found"),
    "empty": (b"", [], "the file is empty"),
    "garbage": (bytes(range(256)) * 40, [], "cannot read it"),
    "nan": ("nan", [], "NaN or infinite"),
    "no_points": (
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
        "property float z\nend_header\n",
        [],
        "no points",
    ),
    "three_points": ("three", [], "only 3 points"),
    "mm_as_m": ("mm", ["--units", "m"], "would be 16"),
    "sphere": ("sphere", [], "does not look like a standing person"),
    "float32_far_away": ("far32", [], "the person is lost"),
    "lying_down": ("zup", [], "or --up if the person is not along Y"),
}


def _scan_file(tmp_path: Path, kind, person: np.ndarray) -> Path:
    path = tmp_path / "scan.ply"
    if kind is None:
        return path
    if isinstance(kind, bytes) or kind.startswith("ply"):
        return _write(path, kind)
    if kind == "nan":
        points = person[:500].copy()
        points[7, 1] = np.nan
        save_ply(path, points)
    elif kind == "three":
        save_ply(path, person[:3])
    elif kind == "mm":
        save_ply(path, person * 1000.0, binary=True)
    elif kind == "sphere":
        save_ply(path, _sphere(), binary=True)
    elif kind == "zup":  # Z up, read as Y up: a person 0.45 m "tall"
        save_ply(path, person[:, [0, 2, 1]], binary=True)
    elif kind == "far32":  # float32 a billion metres out: 64 m between representable numbers
        save_ply(path, person + 1e9, binary=True)
    return path


@pytest.mark.parametrize("case", sorted(SCAN_CASES))
def test_a_bad_scan_is_refused_by_fit_body(case, tmp_path, capsys, person):
    kind, options, words = SCAN_CASES[case]
    path = _scan_file(tmp_path, kind, person)
    out = tmp_path / "body"
    _refused(["fit-body", str(path), "--out", str(out), *options], capsys, words)
    assert not out.exists()


@pytest.mark.parametrize("case", ["sphere", "mm_as_m"])
def test_a_bad_scan_is_refused_by_fit_before_its_folder_is_touched(case, tmp_path, capsys, person):
    kind, options, words = SCAN_CASES[case]
    path = _scan_file(tmp_path, kind, person)
    out = tmp_path / "fit"
    _refused(["fit", str(path), "--garment", "skirt", "--out", str(out), *options], capsys, words)
    assert not out.exists()


def test_a_scan_file_too_large_is_refused_before_reading(tmp_path, capsys, monkeypatch, person):
    path = tmp_path / "scan.ply"
    save_ply(path, person, binary=True)
    monkeypatch.setattr(scan, "MAX_SCAN_BYTES", 1000)
    _refused(["fit-body", str(path), "--out", str(tmp_path / "b")], capsys, "GB read whole here")


def test_a_ply_promising_more_points_than_it_holds_is_refused(tmp_path, capsys, person):
    """A header that promises 4 billion points: read as it streams, the file ends; nothing is allocated."""
    path = tmp_path / "scan.ply"
    save_ply(path, person[:1000], binary=True)
    path.write_bytes(path.read_bytes().replace(b"element vertex 1000", b"element vertex 4000000000"))
    _refused(["fit-body", str(path), "--out", str(tmp_path / "b")], capsys, "the file ends before them")


def test_max_points_below_a_person_is_refused(tmp_path, capsys):
    argv = ["fit-body", str(DEMO_SCAN), "--out", str(tmp_path / "b"), "--max-points", "10"]
    _refused(argv, capsys, "--max-points must be at least 100, got 10")
    assert not (tmp_path / "b").exists()


def test_far_coordinates_in_float64_are_moved_to_the_origin_and_said(tmp_path, person):
    path = tmp_path / "far.ply"
    save_ply(path, person[::20] + np.array([1e9, 0.0, -1e9]))  # ASCII, float64: nothing lost
    points, report = intake_scan(path, clean=False)
    assert np.abs(points.points).max() < 3.0
    assert report.shift is not None and any("too far for float32" in m for m in report.messages)


def test_a_body_fit_far_from_the_scan_warns():
    assert body_fit_warnings(None) == [] and body_fit_warnings(0.015) == []
    assert "the body fit ends 5.0 cm from the scan" in body_fit_warnings(0.05)[0]


# -- patterns: refused before the scan is read ------------------------------------------------------------


def _scaled_pattern(tmp_path: Path, factor: float) -> Path:
    pattern = copy.deepcopy(load_template("skirt"))
    for panel in pattern.panels.values():
        panel.vertices = np.asarray(panel.vertices) * factor
    path = tmp_path / "pattern.json"
    save_pattern(pattern, path)
    return path


@pytest.mark.parametrize(
    ("case", "words"),
    [
        ("nested", "nested too deeply"),
        ("huge", "vertices at spacing"),
        ("tiny", "less than the mesh spacing"),
        ("many", "more than the 200 read here"),
    ],
)
@pytest.mark.parametrize("garment_type", [None, "skirt"])
def test_a_bad_pattern_is_refused(case, words, garment_type, tmp_path, capsys):
    if case == "nested":
        pattern = _write(tmp_path / "pattern.json", "[" * 100000 + "]" * 100000)
    elif case == "many":
        data = pattern_to_dict(load_template("skirt"))
        panel = next(iter(data["pattern"]["panels"].values()))
        data["pattern"]["panels"] = {f"p{k}": panel for k in range(MAX_PANELS + 1)}
        data["pattern"]["stitches"] = []
        pattern = _write(tmp_path / "pattern.json", json.dumps(data))
    else:
        pattern = _scaled_pattern(tmp_path, 1000.0 if case == "huge" else 1e-6)
    out = tmp_path / "fit"
    argv = ["fit", str(DEMO_SCAN), "--garment", str(pattern), "--out", str(out)]
    _refused(argv + (["--garment-type", garment_type] if garment_type else []), capsys, words)
    assert not out.exists()


# -- other JSON files a command reads: strict, before any work ---------------------------------------------

NESTED_JSON = "[" * 100000 + "]" * 100000  # Python's parser recurses: a RecursionError, not a message


@pytest.mark.parametrize(
    ("text", "words"),
    [(NESTED_JSON, "JSON nested too deeply"), ('{"betas": [NaN]}', "NaN is not a JSON number")],
    ids=["nested", "nan"],
)
@pytest.mark.parametrize("option", ["fit --body", "make-scan --pose"])
def test_a_bad_json_file_is_refused(option, text, words, tmp_path, capsys):
    command, flag = option.split()
    path = _write(tmp_path / "given.json", text)
    out = tmp_path / "out"
    scan = [str(DEMO_SCAN), "--garment"] if command == "fit" else []
    _refused([command, *scan, "skirt", flag, str(path), "--out", str(out)], capsys, words)
    assert not out.exists()


# -- configs: refused before the scan is read ------------------------------------------------------------


@pytest.mark.parametrize(
    ("line", "words"),
    [
        ("max_retries: -5", "max_retries must be an integer >= 0"),
        ('keep_best: "false"', "keep_best must be true or false"),
        ("lr_cage: .inf", "lr_cage must be a finite number"),
        ("max_drape_jump: .nan", "max_drape_jump must be a finite number"),
        ("iterations: many", "iterations"),
        ("initial_bend_stiffness: .inf", "initial_bend_stiffness must be in"),
        ('cage: "no"', "cage must be true or false"),
        ("spacing: 100", "less than the mesh spacing 100 m"),
        ("[1, 2", "config.yaml"),
    ],
)
def test_a_bad_config_is_refused(line, words, tmp_path, capsys):
    config = _write(tmp_path / "config.yaml", line + "\n")
    out = tmp_path / "fit"
    argv = ["fit", str(DEMO_SCAN), "--garment", "skirt", "--config", str(config), "--out", str(out)]
    _refused(argv, capsys, words)
    assert not out.exists()


@pytest.mark.parametrize("command", ["fit-body", "segment"])
def test_body_fit_workers_below_one_are_refused(command, tmp_path, capsys):
    out = tmp_path / ("b" if command == "fit-body" else "g.ply")
    extra = ["--garment", "tshirt"] if command == "segment" else []
    argv = [command, str(DEMO_SCAN), *extra, "--out", str(out), "--workers", "0"]
    _refused(argv, capsys, "--workers must be >= 1, got 0")
    assert not out.exists()


@pytest.mark.parametrize("option", ["--workers", "--race-workers"])  # the old spelling still taken
@pytest.mark.parametrize("workers", ["0", "-2"])
def test_workers_below_one_are_refused(option, workers, tmp_path, capsys):
    out = tmp_path / "fit"
    argv = ["fit", str(DEMO_SCAN), "--garment", "skirt", "--out", str(out), f"{option}={workers}"]
    _refused(argv, capsys, f"--workers must be >= 1, got {workers}")
    assert not out.exists()


# -- output folders: refused before any work ------------------------------------------------------------


@pytest.mark.parametrize("command", ["fit", "fit-body", "segment"])
def test_an_output_under_a_file_is_refused(command, tmp_path, capsys):
    blocker = _write(tmp_path / "file", "x")
    out = blocker / "sub" / ("g.ply" if command == "segment" else "out")
    extra = {"fit": ["--garment", "skirt"], "segment": ["--garment", "skirt"]}.get(command, [])
    _refused([command, str(DEMO_SCAN), "--out", str(out), *extra], capsys, "is a file, not a folder")
    assert blocker.read_text() == "x"


@pytest.mark.parametrize(
    "argv",
    [
        ["mesh", "skirt", "--out", "OUT.obj"],
        ["mesh", "skirt", "--svg", "OUT.svg"],
        ["drape", "skirt", "--out", "OUT.obj"],
        ["drape", "skirt", "--out", "d.obj", "--png", "OUT.png"],
        ["make-scan", "skirt", "--out", "OUT"],
        ["animate", "assets", "--out", "OUT"],
        ["demo", "--out", "OUT"],
    ],
    ids=lambda argv: " ".join(argv[:1] + argv[-2:-1]),
)
def test_an_output_of_another_command_under_a_file_is_refused(argv, tmp_path, capsys):
    """Refused at once, not after the drape: each file or folder option whose folder is under a file."""
    blocker = _write(tmp_path / "file", "x")
    argv = [str(blocker / "sub" / a) if a.startswith("OUT") else a for a in argv]
    _refused(argv, capsys, "is a file, not a folder")
    assert blocker.read_text() == "x"


def test_an_unwritable_output_is_refused(read_only_folder, capsys):
    out = read_only_folder / "b"
    _refused(["fit-body", str(DEMO_SCAN), "--out", str(out)], capsys, "is not writable")


def test_resuming_with_another_scan_leaves_the_folder_as_it_was(tmp_path, capsys, person):
    first, other = tmp_path / "first.ply", tmp_path / "other.ply"
    save_ply(first, person[::10], binary=True)
    save_ply(other, person[1::10], binary=True)
    out = tmp_path / "fit"
    out.mkdir()
    config = load_config(None, garment="skirt", template="skirt")
    prepare_kw = dict(units=None, up=None, pattern=None, garment_type=None, body_params=None)
    atomic_save({"fingerprint": fit_fingerprint(first, config, **prepare_kw)}, out / SETUP)
    _write(out / "report.json", "{}")
    before = sorted(p.name for p in out.iterdir())
    argv = ["fit", str(other), "--garment", "skirt", "--out", str(out), "--resume"]
    _refused(argv, capsys, "was made from another scan file")
    assert sorted(p.name for p in out.iterdir()) == before  # no INCOMPLETE, no new config.yaml
    assert not (out / INCOMPLETE).exists() and not (out / RESOLVED_CONFIG).exists()


def test_segment_finding_no_garment_writes_nothing(tmp_path, capsys, default_body):
    from torch_diffavatar.mesh_io import write_obj

    verts, faces = (np.asarray(t) for t in default_body)
    body_dir = tmp_path / "body"
    body_dir.mkdir()
    write_obj(body_dir / "body.obj", verts, faces)
    bare = tmp_path / "bare.ply"
    save_ply(bare, verts, binary=True)  # a bare body: no skirt on it
    out = tmp_path / "seg" / "skirt.ply"
    argv = ["segment", str(bare), "--garment", "skirt", "--body", str(body_dir), "--out", str(out)]
    _refused(argv, capsys, "no skirt points found", "nothing written", progress=True)
    assert not out.exists() and not out.with_suffix(".boundaries.json").exists()


def test_a_non_finite_result_is_one_line_and_no_file(tmp_path, capsys, monkeypatch):
    """A fit whose result holds a NaN (a blown-up material) ends in one line; the JSON is not written."""
    import torch_diffavatar.commands.fit as commands
    from torch_diffavatar.json_io import write_json

    out = tmp_path / "fit"
    monkeypatch.setattr(
        commands,
        "fit_scan",
        lambda *a, **k: write_json(out / "material.json", {"bend_stiffness": float("inf")}),
    )
    out.mkdir()
    argv = ["fit", str(DEMO_SCAN), "--garment", "skirt", "--out", str(out)]
    _refused(argv, capsys, "$.bend_stiffness is not a finite number")
    assert list(out.iterdir()) == []


@pytest.mark.parametrize(
    "error",
    [
        MemoryError(
            "Unable to allocate 6.3 GiB for an array with shape (50000000, 17) and data type float64"
        ),
        RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 137438953472 bytes."),
    ],
    ids=["numpy", "torch"],
)
def test_running_out_of_memory_is_one_line(error, tmp_path, capsys, monkeypatch):
    """numpy's MemoryError and torch's allocator RuntimeError: one line with the size, not a traceback."""
    import torch_diffavatar.commands.fit as commands

    def too_big(*args, **kwargs):
        raise error

    monkeypatch.setattr(commands, "fit_scan", too_big)
    argv = ["fit", str(DEMO_SCAN), "--garment", "skirt", "--out", str(tmp_path / "fit")]
    _refused(argv, capsys, "out of memory (", "GiB asked)", "coarser --spacing")


def test_another_runtime_error_keeps_its_traceback(tmp_path, monkeypatch):
    """Only a failed allocation is the input's fault; any other RuntimeError is a bug and says where."""
    import torch_diffavatar.commands.fit as commands

    def bug(*args, **kwargs):
        raise RuntimeError("shape mismatch")

    monkeypatch.setattr(commands, "fit_scan", bug)
    with pytest.raises(RuntimeError, match="shape mismatch"):
        cli.main(["fit", str(DEMO_SCAN), "--garment", "skirt", "--out", str(tmp_path / "fit")])


def test_ctrl_c_is_one_line_and_says_how_to_continue(tmp_path, capsys, monkeypatch):
    """Ctrl-C during a fit: no traceback, one line that says how to go on, exit status 130 (SIGINT's)."""
    import torch_diffavatar.commands.fit as commands

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(commands, "fit_scan", interrupted)
    code = cli.main(["fit", str(DEMO_SCAN), "--garment", "skirt", "--out", str(tmp_path / "fit")])
    err = capsys.readouterr().err
    assert code == 130 and "Traceback" not in err
    assert err.strip().splitlines() == [
        "diffavatar fit: interrupted; --resume continues from the last checkpoint"
    ]


def test_a_doubtful_shape_warns_and_a_person_passes(person):
    from torch_diffavatar.scan_intake import check_person_shape

    assert check_person_shape(person, "scan.ply") == []
    # a box 1.7 m tall, 1.2 m wide and 0.9 m deep: its depth is about 0.5 of its height
    column = np.random.default_rng(0).uniform([-0.6, 0.0, -0.45], [0.6, 1.7, 0.45], (5000, 3))
    (message,) = check_person_shape(column, "scan.ply")
    assert "unusually deep for a person" in message


def test_an_upside_down_scan_is_a_warning_of_the_intake(tmp_path, person):
    """Upside down with no floor to tell (weak evidence): the intake goes on, and its warnings (a fit
    copies them into report.json) say so and name the fix."""
    path = tmp_path / "scan.ply"
    save_ply(path, person[::4] * np.array([1.0, -1.0, -1.0]), binary=True)
    with pytest.warns(scan.ScanWarning):
        _, report = intake_scan(path)
    assert report.up == "y" and any("upside down" in w and "--up -y" in w for w in report.warnings)
