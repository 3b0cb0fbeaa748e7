"""Training data that does not have to fit in memory: a data set's shards (docs/DATA.md) read
lazily, a few at a time, shuffled across shards.

`ShardSet` indexes a data set without reading its arrays (sample counts and the largest point
count come from `points_count` alone). `IndexSampler` decides which global sample indices make up
each batch; it never touches data, so it is cheap to checkpoint and to replay. `ShardLoader`
gathers a batch's rows from the shards it needs, keeping at most a bounded number of shards in
memory and reading the next window's shards on a background thread.

When the whole set fits in the memory budget there is one window, the set itself, and the
sampler's order is exactly a fresh permutation of every usable index per epoch (what the trainer
did before it streamed); otherwise each epoch visits the shards in a random order, `window`
shards at a time, and permutes the samples inside each window.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from .data import KEYS, read_meta, shard_paths

# Keys whose second axis is the point cap: padded (or trimmed) to the set's largest point count.
POINT_KEYS = ("points_xyz", "points_uv")


class ShardSet:
    """A data set's shards, indexed: per-shard sample counts, global offsets, the largest point
    count, and the bytes one shard's arrays take (per key) for memory budgeting."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.meta, self.cfg = read_meta(self.root)
        self.paths = shard_paths(self.root)
        counts, widest, member_bytes = [], 1, {}
        for path in self.paths:
            with np.load(path) as z:
                missing = [k for k in KEYS if k not in z.files]
                if missing:
                    raise KeyError(f"{path}: missing keys {missing} (from an older posefuse)")
                pc = z["points_count"]
                for info in z.zip.infolist():  # uncompressed members: file_size is the array's bytes
                    key = info.filename.removesuffix(".npy")
                    member_bytes[key] = max(member_bytes.get(key, 0), info.file_size)
            counts.append(len(pc))
            widest = max(widest, int(pc.max(initial=0)))
        self.counts = np.asarray(counts, np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])
        self.points_width = widest
        self._member_bytes = member_bytes

    def __len__(self) -> int:
        return int(self.offsets[-1])

    @property
    def num_shards(self) -> int:
        return len(self.paths)

    def shard_of(self, index: np.ndarray) -> np.ndarray:
        return np.searchsorted(self.offsets, index, side="right") - 1

    def shard_bytes(self, keys) -> int:
        """An upper bound of one shard's bytes in memory for these keys."""
        return sum(self._member_bytes.get(k, 0) for k in keys)

    def read(self, shard: int, keys) -> dict:
        """One shard's arrays for `keys`; point arrays padded to the set's largest point count."""
        out = {}
        with np.load(self.paths[shard]) as z:
            for k in keys:
                a = z[k]
                if k in POINT_KEYS:
                    p = self.points_width
                    a = a[:, :p]
                    if a.shape[1] < p:
                        a = np.pad(a, ((0, 0), (0, p - a.shape[1]), (0, 0)))
                out[k] = a
        return out

    def read_all(self, keys) -> dict:
        """Every shard's arrays for `keys`, concatenated (only for small keys or small sets)."""
        parts = [self.read(i, keys) for i in range(self.num_shards)]
        return {k: np.concatenate([p[k] for p in parts], axis=0) for k in keys}

    def describe(self) -> dict:
        return {
            "path": str(self.root),
            "samples": len(self),
            "shards": self.num_shards,
            "meta": {k: v for k, v in self.meta.items() if k != "preprocessing"},
        }


def window_shards(shards: ShardSet, keys, memory_mb: float) -> int:
    """How many shards one window may hold: the loader keeps up to two windows (the current one
    and the previous, whose last samples may share a batch with the current one's first) and reads
    a third ahead, so a window is a third of the budget, at least one shard."""
    per = max(1, shards.shard_bytes(keys))
    return int(max(1, min(shards.num_shards, (memory_mb * 1e6 / 3) // per)))


class IndexSampler:
    """Endless batches of global sample indices (only those in `usable`), deterministic in its seed
    generator; `state_dict` / `load_state_dict` make a run resumable to the same batches."""

    def __init__(self, shards: ShardSet, usable: np.ndarray, batch_size: int, window: int, rng):
        self.shard_counts = shards.counts
        self.offsets = shards.offsets
        self.usable = np.asarray(usable, bool)
        if len(self.usable) != len(shards):
            raise ValueError("usable mask and data set differ in length")
        self.batch_size = batch_size
        self.window = max(1, min(window, shards.num_shards))
        self.rng = rng
        self.queue = np.empty(0, np.int64)
        self.pending: list[list[int]] = []  # the rest of this epoch's windows

    @property
    def whole(self) -> bool:
        return self.window >= len(self.shard_counts)

    def _usable_in(self, window: list[int]) -> np.ndarray:
        idx = np.concatenate([np.arange(self.offsets[s], self.offsets[s + 1]) for s in window])
        return idx[self.usable[idx]]

    def _next_window(self) -> list[int]:
        if not self.pending:
            n = len(self.shard_counts)
            if self.whole:
                self.pending = [list(range(n))]
            else:
                order = self.rng.permutation(n).tolist()
                self.pending = [order[i : i + self.window] for i in range(0, n, self.window)]
        return self.pending.pop(0)

    def upcoming_shards(self) -> list[int]:
        """The shards of the window the sampler reads next (for prefetching), if known."""
        return list(self.pending[0]) if self.pending else []

    def next(self) -> np.ndarray:
        guard = 0
        while len(self.queue) < self.batch_size:
            idx = self._usable_in(self._next_window())
            self.queue = np.concatenate([self.queue, self.rng.permutation(idx)])
            guard = guard + 1 if len(idx) == 0 else 0
            if guard > 2 * len(self.shard_counts) + 1:
                raise ValueError("no usable sample in the data set")
        batch, self.queue = self.queue[: self.batch_size], self.queue[self.batch_size :]
        return batch

    def state_dict(self) -> dict:
        return {
            "rng": self.rng.bit_generator.state,
            "queue": self.queue.tolist(),
            "pending": [list(w) for w in self.pending],
        }

    def load_state_dict(self, state: dict) -> None:
        self.rng.bit_generator.state = state["rng"]
        self.queue = np.asarray(state["queue"], np.int64)
        self.pending = [list(w) for w in state["pending"]]


class ShardLoader:
    """Gathers rows of `keys` by global index, reading shards on demand. At most `capacity`
    shards stay in memory (least recently used out first); `transform(shard, arrays)` may derive
    arrays once per shard load (e.g. the camera net's heatmaps) and drop what is no longer needed.
    `prefetch` reads shards on one background thread (I/O only; transforms run on the caller's)."""

    def __init__(self, shards: ShardSet, keys, capacity: int, transform=None):
        self.shards = shards
        self.keys = tuple(keys)
        self.capacity = max(1, capacity)
        self.transform = transform
        self.cache: OrderedDict[int, dict] = OrderedDict()
        self.loads = 0
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="shards")
        self._inflight: dict[int, Future] = {}
        self._lock = threading.Lock()

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def prefetch(self, shard_ids) -> None:
        with self._lock:
            for s in shard_ids:
                if s not in self.cache and s not in self._inflight:
                    self._inflight[s] = self._pool.submit(self.shards.read, s, self.keys)

    def _shard(self, s: int) -> dict:
        if s in self.cache:
            self.cache.move_to_end(s)
            return self.cache[s]
        with self._lock:
            fut = self._inflight.pop(s, None)
        arrays = fut.result() if fut is not None else self.shards.read(s, self.keys)
        if self.transform is not None:
            arrays = self.transform(s, arrays)
        self.loads += 1
        self.cache[s] = arrays
        while len(self.cache) > self.capacity:
            self.cache.popitem(last=False)
        return arrays

    def gather(self, index: np.ndarray) -> dict:
        """Rows `index` (global, any order) of every array, in the order given."""
        index = np.asarray(index, np.int64)
        shard = self.shards.shard_of(index)
        out: dict[str, np.ndarray] = {}
        for s in np.unique(shard):
            arrays = self._shard(int(s))
            rows = np.flatnonzero(shard == s)
            local = index[rows] - self.shards.offsets[s]
            for k, a in arrays.items():
                if k not in out:
                    out[k] = np.empty((len(index), *a.shape[1:]), a.dtype)
                out[k][rows] = a[local]
        return out
