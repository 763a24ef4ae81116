"""Writes the tiny KITTI-layout tree the tests use: ``python tests/make_tiny_kitti.py OUT``."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import write_tiny_kitti  # noqa: E402

if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "/tmp/pcfbench-tiny-kitti")
    write_tiny_kitti(out, sequences=("08", "09"), num_sweeps=40)
    print(out)
