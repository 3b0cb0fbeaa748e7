import sys
from pathlib import Path

import pytest

# the tests' helpers, and models-export itself: the library and the experiments and tools packages
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from synthetic import write_dataset  # noqa: E402

GOLDEN = Path(__file__).resolve().parents[2] / "tests" / "golden"


@pytest.fixture(scope="session")
def synthetic_sets(tmp_path_factory):
    """(train_dir, test_dir): tiny shard sets in the simulator's format, different seeds."""
    root = tmp_path_factory.mktemp("data")
    train = write_dataset(root / "train", 96, seed=1, image_size=32, num_points=64, cap=96, shard_size=40)
    test = write_dataset(root / "test", 32, seed=2, image_size=32, num_points=64, cap=96)
    return train, test
