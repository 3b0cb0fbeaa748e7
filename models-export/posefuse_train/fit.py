"""One command from a data set to a served bundle: the camera net, then the fusion and the
LiDAR-only point nets behind it, the bundle exported and scored on the test set through the
server's evaluation path (bundle_eval), its manifest recording the recipe, the data, the command,
the versions, the metrics and the time.

    python -m posefuse_train fit --train data/street_train --test data/street_test --out models/mine

A run keeps its state in a work directory (default: OUT.work): the resolved recipe, log.jsonl
(losses every 50 steps, the held-out metrics at the end), each round's pseudo labels
(labelsN.npz), each stage's resumable checkpoint and, once a stage is done, its network
(camera.pt, fusion.pt, lidar.pt). `--resume` continues an interrupted run from there to the same
weights as an uninterrupted one (same device and number of processes). Under `torchrun
--nproc-per-node N` the stages run data-parallel (DDP); rank 0 writes everything.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import re
import shlex
import shutil
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import onnx
import onnxruntime
import torch

from . import __version__, bundle_eval, distributed
from . import recipe as recipes
from .camera_net import CameraNet, FlipTest, as_served
from .export import camera_from_checkpoint, export_bundle, load_checkpoint, point_from_checkpoint, sha256
from .facing_net import FacingPointNet
from .metrics import CONVENTION
from .point_net import Blend
from .shards import ShardSet
from .train import (
    LABEL_KEYS,
    RunOptions,
    Stopped,
    checkpoint,
    label_settings,
    next_round_labels,
    stream_labels,
    train_camera,
    train_point,
)

# and fusionN, lidarN: round N of a self-trained recipe (point.self_train, point.self_train_rounds)
STAGES = ("camera", "fusion", "lidar")


@dataclass
class FitArgs:
    train: Path
    test: Path
    out: Path
    recipe: str = "cpu"
    overrides: tuple[str, ...] = ()
    work: Path | None = None
    device: str = "auto"
    amp: str = "auto"  # auto: the recipe's on CUDA, none on the CPU
    resume: bool = False
    stop_after: str = ""  # STAGE:STEP, e.g. fusion:200: stop there (checkpoint written)
    memory_mb: float = 3000.0
    checkpoint_every: int = 0  # 0: the recipe's
    name: str = "default"
    version: str = __version__
    threads: int = 0
    command: str = ""
    # another run's work directory whose point nets (trained with rotation over [0, 2π)) read the
    # facing in front of this run's (docs/TRAINING.md, "A bundle that needs no heading")
    facing_from: Path | None = None
    facing_turns: int = 1
    facing_passes: int = 1
    facing_agree_deg: float = 0.0
    # the fusion graph answers the mean of the fusion and LiDAR-only nets (docs/TRAINING.md,
    # "Blending the point networks")
    blend: bool = False


def resolve_device(device: str) -> str:
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise SystemExit("--device cuda: PyTorch sees no CUDA device (docs/TRAINING.md, 'GPUs')")
    return device


def versions() -> dict:
    commit = None
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        pass
    return {
        "posefuse_train": __version__,
        "git_commit": commit,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "onnx": onnx.__version__,
        "onnxruntime": onnxruntime.__version__,
    }


def max_rss_mb() -> float | None:
    """This process's peak resident memory so far (Linux and macOS), MB."""
    try:
        import resource
    except ImportError:  # pragma: no cover - Windows
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 2**10), 1)


class Log:
    """log.jsonl of the run (rank 0): one JSON object a line, each with its time."""

    def __init__(self, path: Path, enabled: bool):
        self.path, self.enabled = path, enabled

    def __call__(self, record: dict) -> None:
        if not self.enabled:
            return
        record = {"time": round(time.time(), 3), **record, "max_rss_mb": max_rss_mb()}
        with open(self.path, "a") as f:
            f.write(json.dumps(record) + "\n")

    def say(self, message: str) -> None:
        if self.enabled:
            print(f"[{time.strftime('%H:%M:%S')}] {message}", flush=True)


def _prepare_work(a: FitArgs, recipe: dict, d: distributed.Dist) -> Path:
    work = Path(a.work) if a.work else a.out.with_name(a.out.name + ".work")
    saved = work / "recipe.json"
    if d.main:
        if work.exists() and not a.resume and any(work.iterdir()):
            raise SystemExit(f"{work} holds an earlier run: --resume to continue it, or remove it")
        work.mkdir(parents=True, exist_ok=True)
        if saved.exists():
            if recipes.dumps(json.loads(saved.read_text())) != recipes.dumps(recipe):
                raise SystemExit(f"{work}: --resume with another recipe than the run's ({saved})")
        else:
            saved.write_text(json.dumps(recipe, indent=2, sort_keys=True) + "\n")
    d.barrier()
    return work


def _stop_at(a: FitArgs, stage: str) -> int:
    if not a.stop_after:
        return 0
    name, _, step = a.stop_after.partition(":")
    if not re.fullmatch(r"camera|(fusion|lidar)([2-9]|[1-9][0-9]+)?", name) or not step.isdigit():
        raise SystemExit(
            f"--stop-after {a.stop_after!r}: expected STAGE:STEP with STAGE in {STAGES} (or fusionN, lidarN)"
        )
    return int(step) if name == stage else 0


def _same_camera(a: FitArgs, work: Path, d: distributed.Dist) -> None:
    """The facing nets were trained on one camera net's heatmaps: this run takes that camera net
    (copied in when it has none yet) and refuses another."""
    source = Path(a.facing_from)
    missing = [n for n in ("camera.pt", "fusion.pt", "lidar.pt") if not (source / n).exists()]
    if missing:
        raise ValueError(f"--facing-from {source}: no {', '.join(missing)} (a finished fit's work directory)")
    if a.facing_turns < 1 or a.facing_passes < 0:
        raise ValueError("--facing-turns must be >= 1 and --facing-passes >= 0")
    mine = work / "camera.pt"
    if d.main and not mine.exists():
        shutil.copyfile(source / "camera.pt", mine)
    d.barrier()
    theirs, ours = (load_checkpoint(p)["state_dict"] for p in (source / "camera.pt", mine))
    if theirs.keys() != ours.keys() or not all(torch.equal(theirs[k], ours[k]) for k in ours):
        raise ValueError(f"--facing-from {source}: its camera net is not this run's ({mine})")


def _with_facing(a: FitArgs, nets: dict) -> tuple[dict, dict]:
    """This run's point nets behind the facing nets of `a.facing_from`, and what the manifest says of it."""
    source = Path(a.facing_from)
    shape = dict(passes=a.facing_passes, turns=a.facing_turns, agree_deg=a.facing_agree_deg)
    firsts = {s: load_checkpoint(source / f"{s}.pt") for s in ("fusion", "lidar")}
    wrapped = {s: FacingPointNet(point_from_checkpoint(firsts[s]), nets[s], **shape) for s in nets}
    about = {"from": str(source), **shape, **{s: firsts[s].get("train_config") for s in firsts}}
    return wrapped, about


def fit(a: FitArgs) -> dict | None:
    """Runs (or resumes) the whole recipe; returns the manifest (rank 0) or None (other ranks,
    or a run stopped by --stop-after)."""
    t_start = time.time()
    device = distributed.local_device(resolve_device(a.device))
    d = distributed.from_env(device)
    if a.threads:
        torch.set_num_threads(a.threads)
    recipe = recipes.load(a.recipe, list(a.overrides))
    work = _prepare_work(a, recipe, d)
    log = Log(work / "log.jsonl", d.main)
    if a.facing_from:
        _same_camera(a, work, d)

    train, test = ShardSet(a.train), ShardSet(a.test)
    want = recipe["recipe"].get("image_size")
    if want and train.cfg.image_size != want:
        raise SystemExit(
            f"recipe {recipe['recipe']['name']!r} is for {want} px crops; {a.train} has "
            f"{train.cfg.image_size} px (simulate/convert with --image-size {want})"
        )
    if train.cfg != test.cfg:
        raise SystemExit(f"train and test preprocessing differ:\n{train.cfg}\n{test.cfg}")
    pipeline = replace(train.cfg, **recipe.get("pipeline", {}))
    run = recipe.get("run", {})
    amp = a.amp if a.amp != "auto" else (run.get("amp", "none") if device.startswith("cuda") else "none")
    base = RunOptions(
        device=device,
        amp=amp == "bf16",
        channels_last=bool(run.get("channels_last", False)) and device.startswith("cuda"),
        memory_mb=a.memory_mb,
        checkpoint_every=a.checkpoint_every or int(run.get("checkpoint_every", 0)),
        resume=a.resume,
        record=log,
        dist=d,
    )
    log(
        {
            "event": "start",
            "command": a.command,
            "recipe": recipe["recipe"]["name"],
            "device": device,
            "processes": d.world,
            "train": train.describe(),
            "test": test.describe(),
        }
    )
    log.say(
        f"fit: {len(train)} train / {len(test)} test persons, S={pipeline.image_size}, recipe "
        f"{recipe['recipe']['name']}, {device} x{d.world}, work {work}"
    )
    timings: dict[str, float] = {}

    def opts(stage: str) -> RunOptions:
        return replace(base, checkpoint=work / f"{stage}.ckpt", stop_at_step=_stop_at(a, stage))

    def done(stage: str) -> Path:
        return work / f"{stage}.pt"

    try:
        # camera net
        net_cfg, cam_cfg = recipes.camera_config(recipe)
        if not done("camera").exists():
            t = time.time()
            camera = train_camera(train, pipeline, net_cfg, cam_cfg, log=log.say, opts=opts("camera"))
            timings["camera_s"] = time.time() - t
            _finish(log, d, camera, pipeline, cam_cfg, a.train, done("camera"), "camera", timings)
        # every process reads the saved net: under DDP each kept its own BatchNorm running
        # statistics, and the fusion features must be the exported camera's
        camera = as_served(camera_from_checkpoint(load_checkpoint(done("camera"))), cam_cfg.flip_test)
        camera = camera.to(device).eval()

        # point nets behind it: one set of pseudo labels for both, and with self-training one
        # set per further round from the round before's nets
        labels = {}

        def labels_of(round_: int, pcfg) -> dict:
            if round_ not in labels:
                first = labels_of(1, pcfg) if round_ > 1 else None
                made_from = (
                    ["camera", *(_stage_name(s, round_ - 1) for s in ("fusion", "lidar"))]
                    if round_ > 1
                    else []
                )
                key = {
                    "round": round_,
                    "train": train.describe(),
                    "settings": label_settings(recipe["data"]["t_r"], pipeline, pcfg, round_),
                    "nets": {n: sha256(done(n)) for n in made_from},
                }
                t = time.time()

                def make() -> dict:
                    if first is None:
                        return stream_labels(train, pipeline, recipe["data"]["t_r"], pcfg)
                    before = tuple(point_from_checkpoint(load_checkpoint(done(n))) for n in made_from[1:])
                    return next_round_labels(train, first, before, camera, pipeline, pcfg, device)

                labels[round_], kept = _kept_labels(work / f"labels{round_}.npz", key, make, d.main)
                timings["labels_s" if round_ == 1 else f"labels{round_}_s"] = time.time() - t
                log(
                    {
                        "event": "labels",
                        "round": round_,
                        "persons": len(labels[round_]["weight"]),
                        "kept": kept,
                    }
                )
            return labels[round_]

        for stage, fusion, round_ in _point_stages(recipe):
            pnet_cfg, pcfg = recipes.point_config(recipe, fusion)
            if done(stage).exists():
                continue
            stage_labels = labels_of(round_, pcfg)
            t = time.time()
            features = camera if fusion else None
            net = train_point(
                train,
                stage_labels,
                features,
                pipeline,
                pnet_cfg,
                pcfg,
                desc=stage,
                log=log.say,
                opts=opts(stage),
            )
            timings[f"{stage}_s"] = time.time() - t
            _finish(log, d, net, pipeline, pcfg, a.train, done(stage), stage, timings)
    except Stopped as stop:
        log({"event": "stopped", "reason": str(stop)})
        log.say(f"{stop}; continue with --resume")
        return None

    if not d.main:
        d.barrier()
        return None
    # the bundle is exported from the saved stage networks: plain modules, the weights on disk
    cam_ckpt = load_checkpoint(done("camera"))
    camera = as_served(camera_from_checkpoint(cam_ckpt), cam_cfg.flip_test)
    last = _point_stages(recipe)[-1][2]
    nets = {
        s: point_from_checkpoint(load_checkpoint(done(_stage_name(s, last)))) for s in ("fusion", "lidar")
    }
    facing = None
    if a.facing_from:
        nets, facing = _with_facing(a, nets)
    if a.blend:
        nets["fusion"] = Blend([nets["fusion"], nets["lidar"]], ["fusion", "lidar"])
    manifest = _export(a, recipe, work, camera, nets, pipeline, train, test, device, d, log, facing)
    timings["total_s"] = time.time() - t_start
    # a resumed run's own timings cover only what it did; the log has every invocation
    runs = run_times(work / "log.jsonl")
    timings.update(runs_s=runs, all_runs_s=round(sum(runs), 1))
    manifest["training"]["time_s"] = {**manifest["training"].get("time_s", {}), **timings}
    text = json.dumps(manifest, indent=2) + "\n"
    (a.out / "manifest.json").write_text(text)
    log({"event": "done", "time_s": timings})
    d.barrier()
    return json.loads(text)


def _kept_labels(path: Path, key: dict, make, write: bool) -> tuple[dict, bool]:
    """A round's pseudo labels as an earlier invocation of this run saved them, when they were made
    from the same data and (after the first round) the same nets, else made now and saved (by
    `write`: rank 0), so that a resumed run does not spend minutes making them again. Returns the
    labels and whether they were the saved ones."""
    text = json.dumps(key, sort_keys=True)
    if path.exists():
        with np.load(path) as saved:
            if str(saved["key"]) == text:
                return {k: saved[k] for k in LABEL_KEYS}, True
    labels = make()
    if write:
        # written whole, then renamed: another process never reads half a file
        part = path.with_name(path.stem + ".part.npz")
        np.savez(part, key=np.array(text), **{k: labels[k] for k in LABEL_KEYS})
        part.replace(path)
    return labels, False


def _point_stages(recipe: dict) -> list[tuple[str, bool, int]]:
    """(stage, fusion, label round) of the point nets, in training order: one round, and with
    self-training `self_train_rounds` more."""
    point = recipe["point"]
    rounds = 1 + (int(point.get("self_train_rounds", 1)) if point.get("self_train", 0.0) > 0 else 0)
    return [(_stage_name(s, r), s == "fusion", r) for r in range(1, rounds + 1) for s in ("fusion", "lidar")]


def _stage_name(net: str, round_: int) -> str:
    return net if round_ == 1 else f"{net}{round_}"


def run_times(log_path: Path) -> list[float]:
    """Wall seconds of each invocation in a run's log.jsonl, oldest first: from its `start` record
    to its last record (an interrupted invocation ends at its last logged step)."""
    runs: list[list[float]] = []
    for line in log_path.read_text().splitlines():
        record = json.loads(line)
        if record.get("event") == "start":
            runs.append([record["time"], record["time"]])
        elif runs:
            runs[-1][1] = record["time"]
    return [round(end - begin, 1) for begin, end in runs]


def _finish(log, d, net, pipeline, cfg, train_path, path: Path, stage: str, timings) -> None:
    """A stage's network saved once it is trained (rank 0), and the resumable state dropped."""
    if d.main:
        torch.save(checkpoint(net, pipeline, cfg, str(train_path)), path)
        ckpt = path.with_suffix(".ckpt")
        if ckpt.exists():
            ckpt.unlink()
        log({"event": "stage_done", "stage": stage, "steps": len(net.loss_history)})
    d.barrier()


def _export(
    a, recipe, work, camera: CameraNet | FlipTest, nets, pipeline, train, test, device, d, log, facing
) -> dict:
    staged = work / "bundle"
    if staged.exists():
        shutil.rmtree(staged)
    cam_cfg = recipes.camera_config(recipe)[1]
    export_bundle(
        staged,
        camera,
        nets["fusion"],
        nets["lidar"],
        pipeline,
        trained=True,
        name=a.name,
        version=a.version,
    )
    t = time.time()
    log.say(f"held-out evaluation of the bundle on {a.test} ({len(test)} persons, ONNX Runtime)")
    metrics = bundle_eval.held_out(staged, test, threads=max(1, torch.get_num_threads()))
    eval_s = time.time() - t
    for mode, m in metrics.items():
        log({"event": "held_out", "mode": mode, **{k: v for k, v in m.items() if not isinstance(v, dict)}})
        pts = m["breakdown"].get("with_points")
        served = (
            f" (persons with points, as `posefuse eval --mode {mode}` scores: "
            f"{100 * (pts['oks_acc_3d'] or 0):.2f} %, {100 * (pts['mpjpe_3d_m'] or 0):.2f} cm)"
            if pts
            else ""
        )
        log.say(
            f"held-out {mode:6s}: OKS/ACC@3D {100 * (m['oks_acc_3d'] or 0):.2f} %, "
            f"MPJPE {100 * (m['mpjpe_3d_m'] or 0):.2f} cm, OKS/ACC@2D {100 * (m['oks_acc_2d'] or 0):.2f} %"
            + served
        )
    manifest = json.loads((staged / "manifest.json").read_text())
    parity = manifest["training"]["config"]["onnx_parity_max_abs_diff"]
    manifest["training"] = {
        "trained": True,
        "recipe": recipe,
        "command": a.command,
        "data": {"train": train.describe(), "test": test.describe()},
        "config": {
            "camera": {**asdict(camera.cfg), **asdict(cam_cfg)},
            "fusion": {**asdict(recipes.point_config(recipe, True)[1]), "net": asdict(nets["fusion"].cfg)},
            "lidar": {**asdict(recipes.point_config(recipe, False)[1]), "net": asdict(nets["lidar"].cfg)},
            "onnx_parity_max_abs_diff": parity,
            **({"facing": facing} if facing else {}),
        },
        "versions": versions(),
        "device": device,
        "processes": d.world,
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {torch.get_num_threads()} torch threads",
        "finished": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "time_s": {"held_out_eval_s": eval_s},
    }
    manifest["metrics"] = {"held_out": metrics, "convention": CONVENTION}
    (staged / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    out = Path(a.out)
    tmp = out.with_name(out.name + ".partial")
    if tmp.exists():
        shutil.rmtree(tmp)
    shutil.copytree(staged, tmp)
    if out.exists():
        shutil.rmtree(out)
    os.replace(tmp, out)
    log({"event": "bundle", "path": str(out)})
    log.say(f"bundle -> {out}")
    return manifest


def command_line(argv) -> str:
    return "python -m posefuse_train " + " ".join(shlex.quote(x) for x in argv)


def main_fit(argv, parser) -> int:
    a = parser.parse_args(argv)
    args = FitArgs(
        train=Path(a.train),
        test=Path(a.test),
        out=Path(a.out),
        recipe=a.recipe,
        overrides=tuple(a.set or ()),
        work=Path(a.work) if a.work else None,
        device=a.device,
        amp=a.amp,
        resume=a.resume,
        stop_after=a.stop_after or "",
        memory_mb=a.memory_mb,
        checkpoint_every=a.checkpoint_every,
        name=a.name,
        version=a.version,
        threads=a.threads,
        command=command_line(["fit", *argv]),
        facing_from=Path(a.facing_from) if a.facing_from else None,
        facing_turns=a.facing_turns,
        facing_passes=a.facing_passes,
        facing_agree_deg=a.facing_agree_deg,
        blend=a.blend,
    )
    # a run ends with a bundle, or stopped on purpose (--stop-after, other ranks): both succeed
    try:
        fit(args)
    except ValueError as e:
        print(f"fit: {e}", file=sys.stderr)
        return 2
    finally:
        distributed.shutdown()
    return 0
