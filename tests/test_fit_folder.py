"""A fit's folder is never a mix of two fits (issue #33): a finished folder is not overwritten unless asked,
an unfinished one says so, and a resume checks that it continues the same scan and settings."""

from __future__ import annotations

import pytest

import torch_diffavatar.fit_setup as fit_setup
from torch_diffavatar.errors import InputError
from torch_diffavatar.fit_config import load_config
from torch_diffavatar.fit_scan import INCOMPLETE, load_setup, prepare_out_folder


def _finished_fit(folder):
    folder.mkdir()
    for name in ("report.json", "pattern.json", "draped.obj", "setup.pt", "config.yaml"):
        (folder / name).write_text("old")
    (folder / "notes.txt").write_text("the user's")
    (folder / "tb").mkdir()
    (folder / "tb" / "events").write_text("old")


def test_a_new_fit_into_a_finished_folder_refuses_without_force(tmp_path):
    out = tmp_path / "fit"
    _finished_fit(out)
    with pytest.raises(InputError, match="holds a fit .*--resume to continue it, --force to replace it"):
        prepare_out_folder(out, resume=False, force=False)
    assert (out / "report.json").read_text() == "old" and not (out / INCOMPLETE).exists()
    prepare_out_folder(out, resume=False, force=True)
    # the earlier fit's files are gone, the user's own file stays, and the folder says it is unfinished
    assert sorted(p.name for p in out.iterdir()) == [INCOMPLETE, "notes.txt"]


def test_an_unfinished_folder_says_so(tmp_path):
    out = tmp_path / "fit"
    prepare_out_folder(out, resume=False, force=False)
    assert (out / INCOMPLETE).is_file()
    with pytest.raises(InputError, match="holds an unfinished fit"):
        prepare_out_folder(out, resume=False, force=False)
    prepare_out_folder(out, resume=True, force=False)  # resuming it is what it is there for


def test_resume_refuses_another_scan_or_other_settings(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(fit_setup, "prepare", lambda *a, **k: calls.append(a) or {"made": len(calls)})
    scan, other = tmp_path / "scan.ply", tmp_path / "other.ply"
    scan.write_text("ply one")
    other.write_text("ply two")
    config = load_config(garment="skirt")
    out = tmp_path / "fit"
    out.mkdir()
    first = load_setup(scan, config, out, resume=False, anny_model=None, units="m", up="y")
    assert first["made"] == 1 and "fingerprint" in first
    # the same scan and settings: the saved set-up, not a new one (more iterations are fine)
    longer = load_config(garment="skirt", iterations=config.iterations + 10)
    assert load_setup(scan, longer, out, resume=True, anny_model=None, units="m", up="y")["made"] == 1
    with pytest.raises(InputError, match="was made from another scan file"):
        load_setup(other, config, out, resume=True, anny_model=None, units="m", up="y")
    with pytest.raises(InputError, match=r"other settings \(spacing, units\)"):
        load_setup(
            scan,
            load_config(garment="skirt", spacing=0.03),
            out,
            resume=True,
            anny_model=None,
            units="cm",
            up="y",
        )
    assert len(calls) == 1


def test_resume_reads_a_set_up_made_before_newer_config_fields(tmp_path, monkeypatch):
    """A set-up saved before a config field existed resumes when the field is at its default (the old fit
    ran as the default does), and is refused when it is not."""
    from torch_diffavatar.fit_checkpoint import atomic_save
    from torch_diffavatar.fit_scan import fit_fingerprint

    monkeypatch.setattr(fit_setup, "prepare", lambda *a, **k: {"made": 1})
    scan = tmp_path / "scan.ply"
    scan.write_text("ply one")
    out = tmp_path / "fit"
    out.mkdir()
    config = load_config(garment="dress")  # the dress keeps the waist fixed and the membrane at 1
    old = fit_fingerprint(scan, config, units="m", up="y")
    for name in ("lr_waist_shift", "waist_shift_bound", "pattern_delay", "initial_stretch"):
        del old["config"][name]
    atomic_save({"made": 0, "fingerprint": old}, out / "setup.pt")
    assert load_setup(scan, config, out, resume=True, anny_model=None, units="m", up="y")["made"] == 0
    with pytest.raises(InputError, match=r"other settings \(pattern_delay\)"):
        load_setup(
            scan, load_config(garment="dress", pattern_delay=3), out, resume=True, anny_model=None,
            units="m", up="y",
        )  # fmt: skip


def test_a_failed_first_sewing_says_which_stage_to_doubt():
    from torch_diffavatar.fit_scan import first_sewing_advice
    from torch_diffavatar.pattern import load_template, mesh_pattern

    garment = mesh_pattern(load_template("skirt"), spacing=0.08)
    sound = {"garment": garment, "scan_boundaries": ["hem", "waist"], "body_fit_chamfer_m": 0.016}
    assert "the template's placement" in first_sewing_advice(sound)
    assert "no hem opening" in first_sewing_advice(dict(sound, scan_boundaries=["waist"]))
    body = first_sewing_advice(dict(sound, body_fit_chamfer_m=0.075))
    assert "the body fit, which ended 7.5 cm from the scan" in body and "--up" in body
    assert "placement" in first_sewing_advice(dict(sound, body_fit_chamfer_m=None))  # a given body
