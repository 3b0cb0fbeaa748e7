import json

from posefuse_train.ablation import ROWS, main


def test_ablation_runs_end_to_end_and_writes_report_and_bundle(synthetic_sets, tmp_path):
    train, test = synthetic_sets
    out, bundle, results = tmp_path / "run", tmp_path / "bundle", tmp_path / "RESULTS.md"
    main(
        [
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
            "--budget-min",
            "0",
            "--camera-epochs",
            "1",
            "--point-epochs",
            "1",
            "--deconv-channels",
            "16",
        ]
    )
    summary = json.loads((out / "results.json").read_text())
    assert set(summary["rows"]) == {"camera", *ROWS}
    for row in summary["rows"].values():
        assert 0.0 <= row["metrics"]["oks_acc_3d"] <= 1.0 and row["metrics"]["count_3d"] == 32
    manifest = json.loads((bundle / "manifest.json").read_text())
    assert manifest["training"]["trained"] is True
    assert set(manifest["metrics"]["held_out"]) == {"fusion", "lidar", "camera"}
    assert manifest["metrics"]["held_out"]["fusion"]["count_3d"] == 32
    md = results.read_text()
    for needle in ("Table 1", "Table 2", "Table 3", "63.14%", "python -m posefuse_train.ablation"):
        assert needle in md
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

    # per-range breakdown of the saved checkpoints, and RESULTS.md re-rendered with it and notes
    from posefuse_train.by_range import main as by_range_main
    from posefuse_train.report import main as report_main

    by_range_main(
        ["--run", str(out), "--test", str(test), "--rows", "camera,lidar_reg_seg,fusion_reg_seg"]
        + ["--json", str(tmp_path / "by_range.json")]
    )
    table = json.loads((tmp_path / "by_range.json").read_text())
    assert sum(c["persons"] for c in table) <= 32 and table
    for c in table:
        assert {"camera", "lidar_reg_seg", "fusion_reg_seg"} <= set(c)
    (tmp_path / "notes.md").write_text("## Our analysis\n\nhand-written")
    report_main(
        [str(out / "results.json"), "--by-range", str(tmp_path / "by_range.json")]
        + ["--notes", str(tmp_path / "notes.md"), "--out", str(tmp_path / "R.md")]
    )
    md = (tmp_path / "R.md").read_text()
    assert "## By range" in md and "## Our analysis" in md and "Table 3" in md

    # a paper-recipe row reusing the camera net: its run directory is self-contained, and the
    # heading-error diagnostic and the report take it
    out2 = tmp_path / "run180"
    main(
        ["--train", str(train), "--test", str(test), "--out", str(out2), "--results", ""]
        + ["--camera-checkpoint", str(out / "camera.pt"), "--rows", "lidar_reg", "--rotate-deg", "180"]
        + ["--budget-min", "0", "--point-epochs", "1"]
    )
    assert (out2 / "camera.pt").read_bytes() == (out / "camera.pt").read_bytes()
    recipe = json.loads((out2 / "results.json").read_text())
    assert recipe["rows"]["lidar_reg"]["config"]["rotate_deg"] == 180.0
    from posefuse_train.heading_error import main as heading_main

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
    report_main(
        [str(out / "results.json"), "--paper-recipe", str(out2 / "results.json")]
        + ["--heading-error", str(tmp_path / "heading.json"), "--out", str(tmp_path / "R2.md")]
    )
    md = (tmp_path / "R2.md").read_text()
    assert "## Table 3 with the paper's rotation augmentation" in md and "## Wrong box headings" in md
