"""`python -m posefuse_train fit`: one command from shards to a scored bundle; the recipes; resuming
an interrupted run to the same weights; two processes (DDP over gloo) against one."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from synthetic import write_dataset

from posefuse_train import recipe as recipes
from posefuse_train.fit import FitArgs, fit, run_times
from posefuse_train.keypoints import K

# A few steps of the cpu recipe, sized for the tests' 32 px synthetic sets.
TINY = (
    "recipe.image_size=32",
    "camera.steps=5",
    "camera.batch_size=16",
    "camera.deconv_channels=16",
    "point.steps=5",
    "point.batch_size=16",
    "point.warmup_steps=2",
    "point.net.local_channels=[16]",
    "point.net.global_channels=[32]",
    "point.net.head_channels=[32]",
    "point.net.seg_channels=[16]",
    "run.checkpoint_every=2",
)
MODELS_EXPORT = Path(__file__).resolve().parents[1]


def args(sets, out: Path, **over) -> FitArgs:
    return FitArgs(train=sets[0], test=sets[1], out=out, overrides=TINY, command="test", **over)


def stage_weights(work: Path) -> dict:
    return {
        s: torch.load(work / f"{s}.pt", weights_only=False)["state_dict"]
        for s in ("camera", "fusion", "lidar")
    }


def equal(a: dict, b: dict) -> bool:
    return all(a[s].keys() == b[s].keys() and all(torch.equal(a[s][k], b[s][k]) for k in a[s]) for s in a)


def records(work: Path) -> list[dict]:
    return [json.loads(line) for line in (work / "log.jsonl").read_text().splitlines()]


@pytest.fixture(scope="module")
def uninterrupted(synthetic_sets, tmp_path_factory):
    out = tmp_path_factory.mktemp("fit") / "bundle"
    manifest = fit(args(synthetic_sets, out))
    return out, manifest


def test_fit_writes_a_scored_bundle_that_states_how_it_was_made(uninterrupted):
    out, manifest = uninterrupted
    assert {p.name for p in out.iterdir()} == {
        "manifest.json",
        "camera.onnx",
        "point_fusion.onnx",
        "point_lidar.onnx",
    }
    assert json.loads((out / "manifest.json").read_text()) == manifest
    t = manifest["training"]
    assert t["trained"] and t["recipe"]["recipe"]["name"] == "cpu" and t["recipe"]["camera"]["steps"] == 5
    assert t["command"] == "test" and t["device"] == "cpu" and t["processes"] == 1
    assert t["versions"]["torch"] == torch.__version__ and t["versions"]["onnxruntime"]
    assert t["data"]["train"]["samples"] == 96 and t["data"]["test"]["samples"] == 32
    assert t["time_s"]["total_s"] > 0 and t["time_s"]["held_out_eval_s"] > 0
    assert t["config"]["fusion"]["depth_correction"] and t["config"]["fusion"]["net"]["in_features"] == 16
    held = manifest["metrics"]["held_out"]
    assert set(held) == {"fusion", "lidar", "camera"}
    assert all(held[m]["count_3d"] > 0 and held[m]["mpjpe_3d_m"] > 0 for m in held)
    # the log: losses of each stage at its checkpoint interval, then the held-out metrics
    log = records(out.with_name("bundle.work"))
    steps = [(r["stage"], r["step"]) for r in log if "loss" in r]
    assert ("camera", 5) in steps and ("fusion", 5) in steps and ("lidar", 5) in steps
    assert not any(stage.endswith("2") for stage, _ in steps)  # no second round unless asked for
    assert all(r["samples_per_s"] > 0 and r["lr"] > 0 for r in log if "loss" in r)
    assert {r["mode"] for r in log if r.get("event") == "held_out"} == {"fusion", "lidar", "camera"}


@pytest.mark.parametrize("stop", ["camera:2", "fusion:3"])
def test_an_interrupted_run_resumes_to_the_same_weights(synthetic_sets, uninterrupted, tmp_path, stop):
    out = tmp_path / "bundle"
    assert fit(args(synthetic_sets, out, stop_after=stop)) is None
    work = out.with_name("bundle.work")
    stage = stop.split(":")[0]
    assert (work / f"{stage}.ckpt").exists() and not (work / f"{stage}.pt").exists()
    assert not out.exists()
    # a second start without --resume refuses to overwrite the run
    with pytest.raises(SystemExit, match="--resume"):
        fit(args(synthetic_sets, out))
    fit(args(synthetic_sets, out, resume=True))
    assert equal(stage_weights(work), stage_weights(uninterrupted[0].with_name("bundle.work")))


def test_the_weights_comparison_can_tell_runs_apart(synthetic_sets, uninterrupted, tmp_path):
    other = tmp_path / "other"
    a = args(synthetic_sets, other)
    a.overrides = (*TINY, "point.seed=1")
    fit(a)
    got, ref = (
        stage_weights(other.with_name("other.work")),
        stage_weights(uninterrupted[0].with_name("bundle.work")),
    )
    assert equal({"camera": got["camera"]}, {"camera": ref["camera"]})  # the camera's seed is its own
    assert not equal({"fusion": got["fusion"]}, {"fusion": ref["fusion"]})


def test_resume_refuses_another_recipe(synthetic_sets, tmp_path):
    out = tmp_path / "bundle"
    fit(args(synthetic_sets, out, stop_after="camera:1"))
    a = args(synthetic_sets, out, resume=True)
    a.overrides = (*TINY, "camera.lr=0.1")
    with pytest.raises(SystemExit, match="another recipe"):
        fit(a)


def test_the_builtin_recipes_load_and_overrides_are_checked():
    assert {"cpu", "paper"} <= set(recipes.builtin())
    paper = recipes.load("paper")
    net, cam = recipes.camera_config(paper)
    assert (net.backbone, cam.steps, cam.batch_size, cam.lr, cam.decay_at) == (
        "resnet50",
        40000,
        1024,
        1e-4,
        (0.5, 0.75),
    )
    pnet, pt = recipes.point_config(paper, fusion=True)
    assert (pt.steps, pt.batch_size, pt.optimizer, pt.lr, pt.rotate_deg, pt.seg_weight) == (
        100000,
        128,
        "sgd",
        1e-3,
        180.0,
        0.1,
    )
    assert paper["recipe"]["image_size"] == 256 and paper["pipeline"]["smoothing_kernel"] == 7
    cpu = recipes.load("cpu", ["camera.steps=7", "camera.backbone=resnet18"])
    assert recipes.camera_config(cpu)[1].steps == 7 and recipes.camera_config(cpu)[0].backbone == "resnet18"
    # a trainer value the recipe leaves at its default can be set; a misspelt one cannot
    assert "occluded_weight" not in recipes.load("cpu")["point"]
    occ = recipes.load("cpu", ["point.occluded_weight=0.5", "point.snap_to_rays=true"])
    assert recipes.point_config(occ, False)[1].occluded_weight == 0.5
    assert recipes.point_config(occ, True)[1].snap_to_rays is True
    assert recipes.point_config(recipes.load("cpu"), False)[1].occluded_weight == 0.0
    flip = recipes.point_config(recipes.load("cpu128-flip"), False)[1]  # the default bundle's
    assert (flip.occluded_weight, flip.snap_to_rays) == (0.5, True)
    misspelt = ("point.nope=1", "point.fusion=false", "point.net.nope=1", "data.nope=1")
    for bad in ("camera.nope=1", "camera=1", "nosuch.steps=1", *misspelt):
        with pytest.raises(ValueError):
            recipes.load("cpu", [bad])
    assert recipes.camera_config(recipes.load("cpu", ["camera.upsample=shuffle"]))[0].upsample == "shuffle"
    with pytest.raises(ValueError, match="upsample must be one of"):
        recipes.load("cpu", ["camera.upsample=bilinear"])
    with pytest.raises(ValueError, match="no recipe"):
        recipes.load("nosuch")


def test_the_default_bundle_is_fit_from_the_built_in_recipe_it_names():
    """The committed bundle was made by `fit --blend` from a built-in recipe (docs/BUNDLE.md,
    "The default bundle"): its manifest records that recipe value for value, the networks and
    steps the recipe resolves to, the command that names it, and a fusion graph that blends the
    two point nets."""
    manifest = json.loads((MODELS_EXPORT.parent / "models" / "default" / "manifest.json").read_text())
    training = manifest["training"]
    name = training["recipe"]["recipe"]["name"]
    assert name in recipes.builtin()
    assert f"--recipe {name} " in training["command"] and " --blend " in training["command"]
    recipe = recipes.load(name)
    assert training["recipe"] == json.loads(json.dumps(recipe))
    cfg = training["config"]
    net, cam = recipes.camera_config(recipe)
    assert {k: cfg["camera"][k] for k in vars(net)} == vars(net)
    assert (cfg["camera"]["steps"], cfg["camera"]["flip_test"]) == (cam.steps, cam.flip_test)
    assert manifest["models"]["camera"].get("flip_test", False) == cam.flip_test
    for stage, fusion in (("fusion", True), ("lidar", False)):
        pnet, pt = recipes.point_config(recipe, fusion)
        assert {k: list(v) if isinstance(v, tuple) else v for k, v in vars(pnet).items()} == cfg[stage]["net"]
        assert cfg[stage]["steps"] == pt.steps, stage
    assert manifest["models"]["point_fusion"]["blend"] == ["fusion", "lidar"]
    pre = manifest["preprocessing"]
    assert pre["image_size"] == recipe["recipe"]["image_size"]
    assert (pre["smoothing_kernel"], pre["smoothing_sigma"]) == (
        recipe["pipeline"]["smoothing_kernel"],
        recipe["pipeline"]["smoothing_sigma"],
    )
    assert training["data"]["train"]["samples"] == 20000
    assert training["data"]["train"]["meta"]["profile"] == "street-hard"


def test_a_recipe_with_a_finer_heatmap_grid_trains_and_exports_it(synthetic_sets, tmp_path):
    """docs/TRAINING.md, "Heatmap resolution" and "Flip test": S/2 heatmaps from a pixel-shuffled
    last conv, sampled bilinearly, asked about the mirror too, from the recipe to the bundle."""
    text = (MODELS_EXPORT / "posefuse_train/recipes/cpu.toml").read_text()
    fine = 'smoothing_sigma = 1.5\nheatmap_size = 16\nsampling = "bilinear"'
    text = text.replace("smoothing_sigma = 3.0", fine)
    text = text.replace("deconv_layers = 3", "deconv_layers = 3\nfinal_shuffle = 2")
    text = text.replace("seed = 0", "flip_test = true\nseed = 0", 1)
    (tmp_path / "fine.toml").write_text(text)
    out = tmp_path / "b"
    manifest = fit(args(synthetic_sets, out, recipe=str(tmp_path / "fine.toml")))
    pre = manifest["preprocessing"]
    assert (pre["image_size"], pre["heatmap_size"], pre["sampling"]) == (32, 16, "bilinear")
    assert manifest["models"]["camera"]["outputs"]["heatmaps"] == [-1, K, 16, 16]
    assert manifest["training"]["config"]["camera"]["final_shuffle"] == 2
    # the mirror pass is in the exported graph and in the heatmaps the fusion net trained on
    assert manifest["models"]["camera"]["flip_test"] is True
    assert manifest["training"]["config"]["camera"]["flip_test"] is True
    assert manifest["metrics"]["held_out"]["fusion"]["count_3d"] > 0
    # without it the camera net trains the same, and the fusion net behind it does not
    (tmp_path / "once.toml").write_text(text.replace("flip_test = true\n", ""))
    once = fit(args(synthetic_sets, tmp_path / "once", recipe=str(tmp_path / "once.toml")))
    assert "flip_test" not in once["models"]["camera"]
    flip, plain = stage_weights(tmp_path / "b.work"), stage_weights(tmp_path / "once.work")
    assert equal({"camera": flip["camera"]}, {"camera": plain["camera"]})
    assert not equal({"fusion": flip["fusion"]}, {"fusion": plain["fusion"]})
    assert equal({"lidar": flip["lidar"]}, {"lidar": plain["lidar"]})


def test_a_recipe_for_another_crop_size_is_refused(synthetic_sets, tmp_path):
    a = args(synthetic_sets, tmp_path / "b")
    a.overrides = tuple(o for o in TINY if not o.startswith("recipe.image_size"))
    with pytest.raises(SystemExit, match="64 px"):
        fit(a)


STEPS = {"camera": 12, "fusion": 60, "lidar": 60}


def _run_fit(sets, out: Path, processes: int) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m"]
    if processes > 1:
        cmd += ["torch.distributed.run", "--standalone", f"--nproc-per-node={processes}", "-m"]
    cmd += ["posefuse_train", "fit", "--train", str(sets[0]), "--test", str(sets[1]), "--out", str(out)]
    cmd += ["--threads", "1", "--device", "cpu"]
    batch = ("camera.batch_size=64", "point.batch_size=64", "run.checkpoint_every=0")
    for o in (*TINY, *batch, f"camera.steps={STEPS['camera']}", f"point.steps={STEPS['fusion']}"):
        cmd += ["--set", o]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(cmd, cwd=MODELS_EXPORT, env=env, capture_output=True, text=True, timeout=600)


def test_two_processes_train_like_one_at_the_same_global_batch(tmp_path):
    """torchrun with two gloo processes, each half of every global batch of 64, against one
    process: the loss of the last 50 steps (12 for the camera) within 2 %. The processes see the
    same samples and augmentations and DDP averages their gradients; what differs is BatchNorm,
    which PyTorch cannot synchronise on the CPU (each process normalises its 32)."""
    train = write_dataset(
        tmp_path / "train", 256, seed=11, image_size=32, num_points=64, cap=96, shard_size=100
    )
    test = write_dataset(tmp_path / "test", 32, seed=12, image_size=32, num_points=64, cap=96)
    one = _run_fit((train, test), tmp_path / "one", 1)
    assert one.returncode == 0, one.stderr[-3000:]
    two = _run_fit((train, test), tmp_path / "two", 2)
    assert two.returncode == 0, two.stderr[-3000:]
    losses = {}
    for name in ("one", "two"):
        log = records(tmp_path / f"{name}.work")
        losses[name] = {r["stage"]: r["loss"] for r in log if "loss" in r and r["step"] == STEPS[r["stage"]]}
        assert [r["processes"] for r in log if r.get("event") == "start"] == [1 if name == "one" else 2]
    assert set(losses["one"]) == set(STEPS)
    for stage, ref in losses["one"].items():
        got = losses["two"][stage]
        print(f"{stage}: one process {ref:.6g}, two {got:.6g} ({100 * (got - ref) / ref:+.2f} %)")
        assert abs(got - ref) <= 0.02 * abs(ref), (stage, ref, got)
    manifest = json.loads((tmp_path / "two" / "manifest.json").read_text())
    assert manifest["training"]["processes"] == 2
    assert np.isfinite(manifest["metrics"]["held_out"]["fusion"]["mpjpe_3d_m"])


def test_a_run_behind_another_runs_facing_nets_exports_a_bundle_that_needs_no_heading(
    synthetic_sets, uninterrupted, tmp_path
):
    first_out, _ = uninterrupted
    first_work = first_out.with_name("bundle.work")
    out = tmp_path / "free"
    manifest = fit(args(synthetic_sets, out, facing_from=first_work, facing_turns=2, facing_agree_deg=30.0))
    work = tmp_path / "free.work"
    # the camera net is the facing nets' own, not trained again
    assert equal(
        {"camera": torch.load(work / "camera.pt", weights_only=False)["state_dict"]},
        {"camera": torch.load(first_work / "camera.pt", weights_only=False)["state_dict"]},
    )
    assert not any(r.get("stage") == "camera" for r in records(work) if "loss" in r)
    facing = manifest["training"]["config"]["facing"]
    assert facing["from"] == str(first_work) and facing["turns"] == 2 and facing["passes"] == 1
    assert facing["agree_deg"] == 30.0 and facing["fusion"]["fusion"] is True
    assert all(manifest["metrics"]["held_out"][m]["count_3d"] > 0 for m in ("fusion", "lidar"))
    # the exported point nets hold both networks: larger than the plain ones of the first run
    for name in ("point_fusion.onnx", "point_lidar.onnx"):
        assert (out / name).stat().st_size > 1.8 * (first_out / name).stat().st_size


def test_facing_nets_behind_another_camera_net_are_refused(synthetic_sets, uninterrupted, tmp_path):
    first_out, _ = uninterrupted
    first_work = first_out.with_name("bundle.work")
    other = tmp_path / "other.work"
    other.mkdir()
    for name in ("fusion.pt", "lidar.pt"):
        (other / name).write_bytes((first_work / name).read_bytes())
    ckpt = torch.load(first_work / "camera.pt", weights_only=False)
    ckpt["state_dict"] = {k: v + 1 if v.is_floating_point() else v for k, v in ckpt["state_dict"].items()}
    torch.save(ckpt, other / "camera.pt")
    work = tmp_path / "mine.work"
    work.mkdir()
    (work / "camera.pt").write_bytes((first_work / "camera.pt").read_bytes())
    with pytest.raises(ValueError, match="not this run's"):
        fit(args(synthetic_sets, tmp_path / "mine", facing_from=other, work=work, resume=True))
    with pytest.raises(ValueError, match="no camera.pt"):
        fit(args(synthetic_sets, tmp_path / "x", facing_from=tmp_path / "nowhere"))


def test_a_facing_weight_gives_the_camera_net_its_facing_head():
    net, train = recipes.camera_config(recipes.load("cpu", ["camera.facing_weight=0.001"]))
    assert net.facing_head and train.facing_weight == 0.001
    net, train = recipes.camera_config(recipes.load("cpu", []))
    assert not net.facing_head and train.facing_weight == 0.0


def test_blend_exports_the_mean_of_the_runs_point_nets_as_its_fusion_graph(
    synthetic_sets, uninterrupted, tmp_path
):
    """docs/TRAINING.md, "Blending the point networks": a finished run's work directory, exported
    again with --blend, trains nothing and scores the blend as its fusion mode."""
    first_out, first = uninterrupted
    work = tmp_path / "bundle.work"
    shutil.copytree(first_out.with_name("bundle.work"), work)
    manifest = fit(args(synthetic_sets, tmp_path / "bundle", work=work, resume=True, blend=True))
    assert manifest["models"]["point_fusion"]["blend"] == ["fusion", "lidar"]
    assert "blend" not in first["models"]["point_fusion"]
    assert equal(stage_weights(work), stage_weights(first_out.with_name("bundle.work")))
    held, before = manifest["metrics"]["held_out"], first["metrics"]["held_out"]
    assert held["lidar"] == before["lidar"] and held["camera"] == before["camera"]
    assert held["fusion"]["mpjpe_3d_m"] != before["fusion"]["mpjpe_3d_m"]
    # the export's own time is seconds; the training it exports is the first invocation's
    runs = manifest["training"]["time_s"]["runs_s"]
    assert len(runs) == 2 and runs[0] >= 0.5 * first["training"]["time_s"]["total_s"]
    assert manifest["training"]["time_s"]["all_runs_s"] == round(sum(runs), 1)
    assert first["training"]["time_s"]["runs_s"] == [first["training"]["time_s"]["all_runs_s"]]


def test_self_training_trains_further_rounds_behind_the_first_and_exports_the_last(
    synthetic_sets, uninterrupted, tmp_path
):
    """docs/TRAINING.md, "Self-training": a finished run's work directory, resumed with
    point.self_train and two rounds, keeps its first round, trains fusion2/lidar2 and then
    fusion3/lidar3, each on labels from the round before's nets, and exports the last."""
    first_out, first = uninterrupted
    work = tmp_path / "bundle.work"
    shutil.copytree(first_out.with_name("bundle.work"), work)
    saved = json.loads((work / "recipe.json").read_text())
    saved["point"].update(self_train=0.5, self_train_rounds=2)
    (work / "recipe.json").write_text(json.dumps(saved))
    a = args(synthetic_sets, tmp_path / "bundle", work=work, resume=True)
    a.overrides = (*TINY, "point.self_train=0.5", "point.self_train_rounds=2")
    manifest = fit(a)
    assert equal(stage_weights(work), stage_weights(first_out.with_name("bundle.work")))
    later = {s: torch.load(work / f"{s}.pt", weights_only=False)["state_dict"] for s in ("lidar2", "lidar3")}
    assert not equal({"x": later["lidar2"]}, {"x": stage_weights(work)["lidar"]})
    assert not equal({"x": later["lidar3"]}, {"x": later["lidar2"]})
    log = records(work)
    assert [r["round"] for r in log if r.get("event") == "labels"][-3:] == [1, 2, 3]
    stages = {(r["stage"], r["step"]) for r in log if "loss" in r}
    assert {("fusion2", 5), ("lidar2", 5), ("fusion3", 5), ("lidar3", 5)} <= stages
    held, before = manifest["metrics"]["held_out"], first["metrics"]["held_out"]
    assert held["lidar"] != before["lidar"] and held["camera"] == before["camera"]
    time_s = manifest["training"]["time_s"]
    assert time_s["labels2_s"] > 0 and time_s["labels3_s"] > 0
    # the bundle is the last round's: exporting round 3's nets again gives its held-out metrics
    work2 = tmp_path / "again.work"
    shutil.copytree(work, work2)
    for net in ("fusion", "lidar"):
        shutil.copyfile(work / f"{net}3.pt", work2 / f"{net}.pt")
    saved["point"].update(self_train=0.0)
    (work2 / "recipe.json").write_text(json.dumps(saved))
    b = args(synthetic_sets, tmp_path / "again", work=work2, resume=True)
    b.overrides = (*TINY, "point.self_train=0.0", "point.self_train_rounds=2")
    assert fit(b)["metrics"]["held_out"]["lidar"] == held["lidar"]
    # --stop-after names a later round's stage
    with pytest.raises(SystemExit, match="fusionN"):
        fit(args(synthetic_sets, tmp_path / "x", stop_after="lidar1:3"))


def self_trained(sets, first_out: Path, work: Path, weight: float, **over) -> FitArgs:
    """A copy of a finished run's work directory (once), resumed with one round of self-training."""
    if not work.exists():
        shutil.copytree(first_out.with_name("bundle.work"), work)
    saved = json.loads((work / "recipe.json").read_text())
    saved["point"].update(self_train=weight, self_train_rounds=1)
    (work / "recipe.json").write_text(json.dumps(saved))
    a = args(sets, work.with_name(work.name + ".out"), work=work, resume=True, **over)
    a.overrides = (*TINY, f"point.self_train={weight}", "point.self_train_rounds=1")
    return a


def kept(work: Path) -> list[tuple[int, bool]]:
    return [(r["round"], r["kept"]) for r in records(work) if r.get("event") == "labels"]


def test_a_resumed_run_keeps_the_labels_it_made_while_their_data_settings_and_nets_are_the_same(
    synthetic_sets, uninterrupted, tmp_path
):
    first_out = uninterrupted[0]
    whole = tmp_path / "whole.work"
    fit(self_trained(synthetic_sets, first_out, whole, 0.5))
    # stopped in round 2's LiDAR-only net, then resumed: both rounds' labels are read back, and
    # the weights are the uninterrupted run's
    work = tmp_path / "parts.work"
    assert fit(self_trained(synthetic_sets, first_out, work, 0.5, stop_after="lidar2:3")) is None
    assert (work / "labels1.npz").exists() and (work / "labels2.npz").exists()
    fit(self_trained(synthetic_sets, first_out, work, 0.5))
    assert kept(work)[-2:] == [(1, True), (2, True)]
    assert equal(
        {"x": torch.load(whole / "lidar2.pt", weights_only=False)["state_dict"]},
        {"x": torch.load(work / "lidar2.pt", weights_only=False)["state_dict"]},
    )

    def again(weight: float) -> None:
        for n in ("fusion2", "lidar2"):
            (work / f"{n}.pt").unlink()
        fit(self_trained(synthetic_sets, first_out, work, weight))

    # another self-training weight: the first round's labels stand, the second's are made again
    again(0.25)
    assert kept(work)[-2:] == [(1, True), (2, False)]
    # another first-round net behind the second round's labels: likewise
    state = torch.load(work / "fusion.pt", weights_only=False)
    name = next(iter(state["state_dict"]))
    state["state_dict"][name] = state["state_dict"][name] + 0.01
    torch.save(state, work / "fusion.pt")
    again(0.25)
    assert kept(work)[-2:] == [(1, True), (2, False)]
    again(0.25)
    assert kept(work)[-2:] == [(1, True), (2, True)]


def test_run_times_measure_each_invocation_from_its_start_to_its_last_record(tmp_path):
    records = [
        {"time": 10.0, "event": "start"},
        {"time": 12.5, "loss": 1.0},
        {"time": 40.0, "event": "stopped"},
        {"time": 100.0, "event": "start"},
        {"time": 101.0, "event": "stage_done"},
        {"time": 103.5, "event": "done"},
    ]
    log = tmp_path / "log.jsonl"
    log.write_text("".join(json.dumps(r) + "\n" for r in records))
    assert run_times(log) == [30.0, 3.5]
