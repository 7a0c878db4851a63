"""Where the shipped configs live: ``configs/`` at the repository root, installed inside the
package as ``stewart_calib/configs`` (a link in the source tree), so that a wheel finds them too."""

from importlib import resources
from pathlib import Path

#: ``platforms/``, ``experiments/`` and ``estimators/`` TOML files.
CONFIGS = Path(str(resources.files("stewart_calib") / "configs"))
