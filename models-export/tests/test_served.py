import json
import stat
import sys
from pathlib import Path

import pytest

from experiments import served
from posefuse_train.keypoints import NAMES, PARTS


def metrics(oks3d, mpjpe, oks2d=0.8, wrist=0.5, elbow=0.7, hip=0.9, other=0.6):
    per_part = {"wrist": wrist, "elbow": elbow, "hip": hip}
    per_kp = [None] * len(NAMES)
    for part, idx in PARTS.items():
        for i in idx:
            per_kp[i] = {"name": NAMES[i], "oks": per_part.get(part, other)}
    return {
        "oks_acc_3d": oks3d,
        "mpjpe_3d_m": mpjpe,
        "oks_acc_2d": oks2d,
        "pck_3d_10cm": 0.7,
        "per_keypoint_oks_3d": per_kp,
    }


def write_result(run, name, mode, m):
    d = served.served_dir(run, "req")
    d.mkdir(parents=True, exist_ok=True)
    (d / name).write_text(json.dumps({"mode": mode, "metrics": {"all": {}, mode: m}}))


def test_eval_exports_each_pair_once_and_scores_fusion_lidar_and_the_camera_once(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    for name in (
        "fusion_reg.pt",
        "lidar_reg.pt",
        "fusion_reg_seg_depth.pt",
        "lidar_reg_seg_depth.pt",
        "fusion_reg_seg.pt",
    ):
        (run / name).write_bytes(b"")
    exported, calls = [], []

    def export(camera, fusion, lidar, out):
        exported.append((fusion.name, lidar.name, out.name))
        out.mkdir()
        (out / "manifest.json").write_text("{}")

    def evaluate(posefuse, data, bundle, mode, noise, seed):
        calls.append((bundle.name, mode, noise, seed))
        return {"metrics": {mode: {"bundle": bundle.name}}}

    data = tmp_path / "req"
    written = served.eval_run(run, run / "camera.pt", data, tmp_path / "pf", export=export, evaluate=evaluate)
    # lidar_reg_seg.pt is missing: that row pair is not a bundle
    assert exported == [
        ("fusion_reg.pt", "lidar_reg.pt", "bundle_reg"),
        ("fusion_reg_seg_depth.pt", "lidar_reg_seg_depth.pt", "bundle_reg_seg_depth"),
    ]
    assert [p.name for p in written] == ["fusion_reg.json", "lidar_reg.json", "camera.json"] + [
        "fusion_reg_seg_depth.json",
        "lidar_reg_seg_depth.json",
    ]
    assert all(p.parent == run / "served" / "req" for p in written)
    assert (
        json.loads((run / "served" / "req" / "lidar_reg.json").read_text())["metrics"]["lidar"]["bundle"]
        == "bundle_reg"
    )
    # a second pass, with random headings, reuses the bundles and names its files by the noise
    exported.clear()
    calls.clear()
    written = served.eval_run(
        run, run / "camera.pt", data, tmp_path / "pf", "uniform", 3, export=export, evaluate=evaluate
    )
    assert exported == []
    assert "camera_uniform.json" in [p.name for p in written]
    assert set(c[2:] for c in calls) == {("uniform", 3)}


def test_eval_refuses_a_run_without_a_pair(tmp_path):
    (tmp_path / "fusion_reg.pt").write_bytes(b"")
    with pytest.raises(SystemExit, match="no pair"):
        served.eval_run(tmp_path, tmp_path / "c.pt", tmp_path / "req", tmp_path / "pf")


def fake_posefuse(tmp_path, code=0):
    exe = tmp_path / "posefuse"
    exe.write_text(
        f"#!{sys.executable}\nimport json, sys\n"
        "print(json.dumps({'argv': sys.argv[1:], 'metrics': {}}))\n"
        f"sys.stderr.write('boom')\nsys.exit({code})\n"
    )
    exe.chmod(exe.stat().st_mode | stat.S_IXUSR)
    return exe


def test_posefuse_eval_passes_the_mode_bundle_and_heading_noise(tmp_path):
    out = served.posefuse_eval(fake_posefuse(tmp_path), tmp_path / "d", tmp_path / "b", "lidar", "uniform", 7)
    argv = out["argv"]
    assert argv[:2] == ["eval", "--data"] and argv[argv.index("--mode") + 1] == "lidar"
    assert argv[argv.index("--model-dir") + 1] == str(tmp_path / "b")
    assert (
        argv[argv.index("--heading-noise") + 1] == "uniform" and argv[argv.index("--noise-seed") + 1] == "7"
    )
    exact = served.posefuse_eval(fake_posefuse(tmp_path), tmp_path / "d", tmp_path / "b", "fusion", None, 7)[
        "argv"
    ]
    assert "--heading-noise" not in exact and "--json" in exact


def test_a_failed_eval_is_an_error_with_its_message(tmp_path):
    with pytest.raises(RuntimeError, match="boom"):
        served.posefuse_eval(fake_posefuse(tmp_path, 2), tmp_path / "d", tmp_path / "b", "lidar", None, 0)


def two_seeds(tmp_path):
    runs = [tmp_path / "s0", tmp_path / "s2"]
    for run, (f, lid) in zip(runs, ((0.60, 0.55), (0.62, 0.58)), strict=True):
        write_result(run, "fusion_reg_seg.json", "fusion", metrics(f, 0.09, wrist=0.6))
        write_result(run, "lidar_reg_seg.json", "lidar", metrics(lid, 0.10, wrist=0.45))
        write_result(run, "camera.json", "camera", metrics(0.3, 0.2))
    write_result(runs[0], "fusion_reg.json", "fusion", metrics(0.5, 0.1))
    return runs


def test_tables_average_the_seeds_and_show_each(tmp_path):
    seeds = [served.load_rows(r, "req") for r in two_seeds(tmp_path)]
    assert set(seeds[0]) == {"fusion_reg_seg", "lidar_reg_seg", "camera", "fusion_reg"}
    t1 = served.table1(seeds, "reg_seg")
    line = next(x for x in t1.splitlines() if x.startswith("| multi-modal |"))
    assert "| 61.00 % (60.00 / 62.00) | 9.00 cm (9.00 / 9.00) |" in line and "| 63.14 % |" in line
    t3 = served.table3(seeds)
    # LiDAR rows first, then fusion; a row one seed lacks shows its gap
    first_cells = [x.split("|")[1:5] for x in t3.splitlines()[2:]]
    assert [c[2].strip() for c in first_cells] == ["", "✓", "✓"]
    reg = next(x for x in t3.splitlines() if x.startswith("| ✓ |  | ✓ | eq. 1 |"))
    assert "50.00 % (50.00 / -)" in reg and "62.03 %" in reg
    m = served.margins(seeds)
    line = next(x for x in m.splitlines() if x.startswith("| reg_seg |"))
    # fusion - LiDAR: +5 and +4 OKS points, -1 cm, wrist +15 points; LiDAR wrist/hip 0.5
    assert (
        "| +4.50 pt (+5.00 / +4.00) | -1.00 cm (-1.00 / -1.00) | +15.00 pt (+15.00 / +15.00) "
        "| 0.50 (0.50 / 0.50) |" in line
    )
    t2 = served.table2(seeds, "reg_seg")
    wrist = next(x for x in t2.splitlines() if x.startswith("| wrist |"))
    assert "| +15.00 pt (+15.00 / +15.00) | +16.60 pt |" in wrist


def test_tables_cli_writes_markdown_and_names_runs_without_results(tmp_path):
    runs = two_seeds(tmp_path)
    out = tmp_path / "t.md"
    served.main(["tables", "--data-name", "req", *map(str, runs), "--out", str(out)])
    assert "Table 3" in out.read_text() and "| camera-only |" in out.read_text()
    with pytest.raises(SystemExit, match="empty"):
        served.main(["tables", "--data-name", "req", str(runs[0]), str(tmp_path / "empty")])


def test_the_published_ablation_tables_are_the_committed_reports():
    """docs/RESULTS.md's street-hard ablation tables are what `tables` renders from the served
    reports committed beside it (docs/runs/street-hard/ablation), line for line."""
    root = Path(__file__).resolve().parents[2]
    results = (root / "docs" / "RESULTS.md").read_text()
    runs = [root / "docs" / "runs" / "street-hard" / "ablation" / f"seed{s}" for s in (0, 2)]
    for pair, noise in (("reg_seg", None), ("reg_seg_depth", None), ("reg_seg", "uniform")):
        seeds = [served.load_rows(r, "hard_req_s3", noise) for r in runs]
        assert all(len(s) == 7 for s in seeds), "three pairs in two modes, and the camera"
        tables = [served.table3(seeds), served.margins(seeds)]
        if noise is None:
            tables.append(
                served.table2(seeds, pair) if pair == "reg_seg_depth" else served.table1(seeds, pair)
            )
        for table in tables:
            for line in table.splitlines()[2:]:
                body = (
                    line.split("|", 2)[2]
                    if line.startswith("| LiDAR-only |") or line.startswith("| multi-modal |")
                    else line
                )
                assert body in results, f"not in docs/RESULTS.md: {line}"


def test_a_profile_without_labelled_hips_is_a_gap_not_an_error():
    m = metrics(0.5, 0.1, wrist=0.4, hip=0.8)
    assert served.ratio_to_hips(m, "wrist") == 0.5
    for i in PARTS["hip"]:
        m["per_keypoint_oks_3d"][i]["oks"] = None
    assert served.ratio_to_hips(m, "wrist") is None
    assert served.cell([served.ratio_to_hips(m, "wrist")], 1, "") == "-"
