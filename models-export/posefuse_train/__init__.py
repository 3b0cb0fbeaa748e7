"""posefuse trainer: weakly supervised camera + LiDAR 3D pose networks and their ONNX export."""

import os

# Training shares a small CPU with other work: spinning OpenMP workers then fight other processes
# for the cores and run several times slower than sleeping ones. Must be set before torch loads.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

__version__ = "0.1.0"
