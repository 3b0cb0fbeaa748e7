"""requirements.lock pins every requirement of requirements.txt at one exact version inside its
range, so scripts/setup.sh installs the same packages everywhere (docs/TRAINING.md)."""

from pathlib import Path

from packaging.requirements import Requirement

HERE = Path(__file__).resolve().parents[1]


def requirements(path: Path) -> list[Requirement]:
    lines = (line.split("#", 1)[0].strip() for line in path.read_text().splitlines())
    return [Requirement(line) for line in lines if line]


def test_every_requirement_is_pinned_within_its_range():
    pins = {}
    for r in requirements(HERE / "requirements.lock"):
        specs = list(r.specifier)
        assert len(specs) == 1 and specs[0].operator == "==", f"{r}: not an exact pin"
        pins[r.name.lower().replace("_", "-")] = specs[0].version
    for r in requirements(HERE / "requirements.txt"):
        name = r.name.lower().replace("_", "-")
        assert name in pins, f"{r.name} is not in requirements.lock (bash scripts/lock.sh)"
        assert r.specifier.contains(pins[name], prereleases=True), f"{r.name}=={pins[name]} is outside {r}"


def test_the_lock_holds_what_the_trainer_imports():
    import numpy
    import torch

    pins = {r.name: str(r.specifier)[2:] for r in requirements(HERE / "requirements.lock")}
    assert torch.__version__.split("+")[0] == pins["torch"]
    assert numpy.__version__ == pins["numpy"]
