"""Write the sample ROS bag of the README: the simulated paper platform as a ROS robot records it.

``python examples/ros-bag/make_bag.py`` (re)writes ``run.bag`` (ROS 1) and ``platform.toml`` next to
itself from ``stewart-calib simulate --experiment quick``: the paper's platform with its Table 4
errors, 120 samples at 0 and 40 kg. Each sample is two ``sensor_msgs/JointState`` messages with the
same stamp — ``/drive/joint_states``, the six strokes, and ``/tracker/joint_states``, the in-situ
tracker's six ruler readings, both in metres as ROS publishes them, joints ``leg1 … leg6`` —
stamped ``1 700 000 000 s + t_s``. ``platform.toml`` is the simulation's nominal platform. Run from
a checkout (the messages are built by ``tests/ros_messages.py``, as the tests build theirs;
``pip install -e '.[test]'`` brings rosbags).
"""

from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))  # the checkout, for tests/ros_messages.py

from stewart_calib.cli import main as cli  # noqa: E402 (the checkout joins sys.path first)
from tests.ros_messages import JOINT_STATE, bag_writer, joint_state, stamp_ns  # noqa: E402 (as above)

JOINTS = [f"leg{i}" for i in range(1, 7)]
LEGS = range(1, 7)


def write_bag(log_csv: Path, bag: Path) -> int:
    """``bag`` (ROS 1) from a measurement log of the in-situ tracker; returns the samples written."""
    log = np.genfromtxt(log_csv, delimiter=",", names=True, dtype=float)
    strokes_m = np.column_stack([log[f"q{i}_mm"] for i in LEGS]) / 1000.0
    readings_m = np.column_stack([log[f"s{i}_mm"] for i in LEGS]) / 1000.0
    bag.unlink(missing_ok=True)
    writer, typestore, serialize = bag_writer(bag, "ros1")
    with writer:
        drive = writer.add_connection("/drive/joint_states", JOINT_STATE, typestore=typestore)
        tracker = writer.add_connection("/tracker/joint_states", JOINT_STATE, typestore=typestore)
        for t, q, s in zip(log["t_s"], strokes_m, readings_m, strict=True):
            for connection, positions in ((drive, q), (tracker, s)):
                message = joint_state(typestore, float(t), JOINTS, positions)
                writer.write(connection, stamp_ns(float(t)), serialize(message, connection.msgtype))
    return len(log)


def main(out: Path = HERE) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        simulated = Path(tmp) / "sim"
        if cli(["simulate", "--experiment", "quick", "--out", str(simulated)]) != 0:
            raise SystemExit("simulate failed")
        n = write_bag(simulated / "log.csv", out / "run.bag")
        shutil.copyfile(simulated / "platform.toml", out / "platform.toml")
    print(f"wrote {out / 'run.bag'} ({n} samples) and {out / 'platform.toml'}")


if __name__ == "__main__":
    main()
