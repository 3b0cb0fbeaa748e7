import sys
from pathlib import Path

# The Python client tests' live_server module: where the binary is, and why a test cannot run it.
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "clients" / "python" / "tests"))
