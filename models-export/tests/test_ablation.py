import json
import shlex

from experiments.ablation import ROWS, main
from experiments.report import cm, pct
from posefuse_train.data import load


def test_ablation_runs_end_to_end_and_writes_report_and_bundle(synthetic_sets, tmp_path, monkeypatch, capsys):
    train, test = synthetic_sets
    out, bundle, results = tmp_path / "run", tmp_path / "bundle", tmp_path / "RESULTS.md"
    args = [
        "--train",
        str(train),
        "--test",
        str(test),
        "--out",
        str(out),
        "--bundle",
        str(bundle),
        "--results",
        str(results),
        "--camera-epochs",
        "1",
        "--point-epochs",
        "2",
        "--deconv-channels",
        "16",
    ]
    main(args)
    summary = json.loads((out / "results.json").read_text())
    assert set(summary["rows"]) == {"camera", *ROWS}
    assert summary["command"] == "python -m experiments.ablation " + shlex.join(args)
    for row in summary["rows"].values():
        assert row["metrics"]["count_3d"] == 32
    # every point row ran the same fixed number of steps: 2 epochs of one batch (96 persons < 128)
    assert {summary["rows"][r]["steps"] for r in ROWS} == {2}
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["training"]["trained"] is True
    assert set(manifest["metrics"]["held_out"]) == {"fusion", "lidar", "camera"}
    assert manifest["metrics"]["held_out"]["fusion"]["count_3d"] == 32
    md = results.read_text()
    assert summary["command"] in md
    # Table 3's multi-modal reg + seg line carries this run's numbers beside the paper's
    ours = summary["rows"]["fusion_reg_seg"]["metrics"]
    line = next(x for x in md.splitlines() if x.startswith("| ✓ | ✓ | ✓ | eq. 1 |"))
    assert f"| {pct(ours['oks_acc_3d'])} | {cm(ours['mpjpe_3d_m'])} | {pct(ours['oks_acc_2d'])} |" in line
    assert "| 63.14% | 10.32 cm | 82.94% |" in line
    # the checkpoints it saved re-export through the CLI as a trained bundle
    from posefuse_train.export import main as export_main

    held_out = {
        k: summary["rows"][r]["metrics"]
        for k, r in (("fusion", "fusion_reg_seg"), ("lidar", "lidar_reg_seg"), ("camera", "camera"))
    }
    (tmp_path / "m.json").write_text(json.dumps(held_out))
    export_main(
        [
            "--camera",
            str(out / "camera.pt"),
            "--fusion",
            str(out / "fusion_reg_seg.pt"),
            "--lidar",
            str(out / "lidar_reg_seg.pt"),
            "--metrics",
            str(tmp_path / "m.json"),
            "--out",
            str(tmp_path / "again"),
        ]
    )
    again = json.loads((tmp_path / "again" / "manifest.json").read_text())
    assert again["training"]["trained"] is True and again["metrics"]["held_out"] == held_out
    assert again["preprocessing"] == manifest["preprocessing"]
    assert "flip_test" not in again["models"]["camera"]
    export_main(
        ["--camera", str(out / "camera.pt"), "--fusion", str(out / "fusion_reg_seg.pt")]
        + ["--lidar", str(out / "lidar_reg_seg.pt"), "--flip-test", "--out", str(tmp_path / "flip")]
    )
    assert (
        json.loads((tmp_path / "flip" / "manifest.json").read_text())["models"]["camera"]["flip_test"] is True
    )

    # per-range breakdown of the saved checkpoints, and RESULTS.md re-rendered with it and notes
    from experiments.by_range import main as by_range_main
    from experiments.report import main as report_main

    by_range_main(
        ["--run", str(out), "--test", str(test), "--rows", "camera,lidar_reg_seg,fusion_reg_seg"]
        + ["--json", str(tmp_path / "by_range.json")]
    )
    table = json.loads((tmp_path / "by_range.json").read_text())
    range_m = load(test)[0]["range_m"]
    for c in table:
        lo, hi = (float(x) for x in c["range_m"].split("-"))
        assert c["persons"] == int(((range_m >= lo) & (range_m < hi)).sum()) > 0
        assert {"camera", "lidar_reg_seg", "fusion_reg_seg"} <= set(c)
    assert sum(c["persons"] for c in table) == int(((range_m >= 3) & (range_m < 60)).sum())
    (tmp_path / "notes.md").write_text("## Our analysis\n\nhand-written")
    (tmp_path / "preface.md").write_text("## Metric convention\n\nwhat counts")
    report_main(
        [str(out / "results.json"), "--by-range", str(tmp_path / "by_range.json")]
        + ["--notes", str(tmp_path / "notes.md"), "--preface", str(tmp_path / "preface.md")]
        + ["--out", str(tmp_path / "R.md")]
    )
    md = (tmp_path / "R.md").read_text()
    assert "## Our analysis\n\nhand-written" in md
    # the preface comes first, right after the title
    at = md.index
    assert at("## Metric convention\n\nwhat counts") < at("One command,") < at("## Our analysis")
    # the by-range table: one line per band, with its persons and the rows' measured numbers
    c = table[0]
    cell = f"{pct(c['camera']['oks_acc_3d'])} / {cm(c['camera']['mpjpe_3d_m'])}"
    assert f"| {c['range_m']} | {c['persons']} | {c['mean_points']:.0f} | {cell} |" in md

    # a paper-recipe row reusing the camera net: its run directory is self-contained, nothing is
    # written outside it, and the heading-error diagnostic and the report take it
    out2 = tmp_path / "run180"
    cwd = tmp_path / "cwd"
    cwd.mkdir()
    monkeypatch.chdir(cwd)
    main(
        ["--train", str(train), "--test", str(test), "--out", str(out2)]
        + ["--camera-checkpoint", str(out / "camera.pt"), "--rows", "lidar_reg", "--rotate-deg", "180"]
        + ["--point-epochs", "1", "--flip-test"]
    )
    assert (out2 / "camera.pt").read_bytes() == (out / "camera.pt").read_bytes()
    assert list(cwd.iterdir()) == []
    recipe = json.loads((out2 / "results.json").read_text())
    # the flip test is the camera's answer there; the same net without it answers as in the first run
    flipped = recipe["rows"]["camera"]
    assert (
        flipped["config"]["flip_test"] is True and summary["rows"]["camera"]["config"]["flip_test"] is False
    )
    assert flipped["metrics_without_flip_test"] == summary["rows"]["camera"]["metrics"]
    assert flipped["metrics"] != flipped["metrics_without_flip_test"]
    assert recipe["rows"]["lidar_reg"]["config"]["rotate_deg"] == 180.0
    from experiments.heading_error import main as heading_main

    heading_main(
        ["--test", str(test), "--errors", "0,180", "--json", str(tmp_path / "heading.json")]
        + ["--models", f"{out}:fusion_reg_seg,{out2}:lidar_reg"]
    )
    heading = json.loads((tmp_path / "heading.json").read_text())
    assert [c["error_deg"] for c in heading] == [0.0, 180.0]
    assert (
        heading[0][f"{out}:fusion_reg_seg"]["oks_acc_3d"]
        == summary["rows"]["fusion_reg_seg"]["metrics"]["oks_acc_3d"]
    )
    capsys.readouterr()
    report_main(
        [str(out / "results.json"), "--paper-recipe", str(out2 / "results.json")]
        + ["--heading-error", str(tmp_path / "heading.json")]
    )
    md = capsys.readouterr().out  # without --out the report goes to standard output only
    assert list(cwd.iterdir()) == []
    assert "## Table 3 with the paper's rotation augmentation" in md and "## Wrong box headings" in md
