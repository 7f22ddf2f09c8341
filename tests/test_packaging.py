"""setup.cfg lists every package of the source tree: a package missing there is left out of a
real (non-editable) install, such as the GPU report's, while editable installs still find it."""
import configparser
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_every_package_is_listed_in_setup_cfg():
    cfg = configparser.ConfigParser()
    cfg.read(REPO / "setup.cfg")
    listed = set(cfg["options"]["packages"].split())
    found = {".".join(p.parent.relative_to(REPO).parts) for p in (REPO / "qr_cl").rglob("*.py")
             if "__pycache__" not in p.parts}
    assert found - listed == set(), f"packages missing from setup.cfg: {sorted(found - listed)}"
