"""The A/B harness (bench/ab.py): ``--base`` as an interpreter or a checkout, and the runs of both."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

from ab import THIS, ab_rounds, installs

REPO = Path(__file__).resolve().parents[1]

# a worker that says which qr_cl its process finds (without importing it: that takes seconds)
WORKER = """import importlib.util, json, os, sys
spec = importlib.util.find_spec("qr_cl")
print("noise")
print(json.dumps({"qr_cl": spec.origin, "cwd": os.getcwd(), "argv": sys.argv[1:]}))
"""


def test_without_base_only_this_checkout_runs():
    with installs(None) as runs_of:
        assert runs_of == [THIS]


def test_an_interpreter_runs_as_the_base():
    with installs(sys.executable) as runs_of:
        assert [i.label for i in runs_of] == ["base", "this"]
        assert runs_of[0].python == sys.executable and runs_of[0].env is None


@pytest.mark.parametrize("base", ["/no/such/python", "{tmp}"])
def test_a_base_that_is_neither_fails_in_one_line(base, tmp_path):
    with pytest.raises(SystemExit) as error:
        with installs(base.format(tmp=tmp_path)):
            pass
    message = str(error.value)
    assert message.startswith("--base: ") and "\n" not in message


def test_a_checkout_runs_laid_out_as_installed_beside_this_one(tmp_path, capsys):
    worker = tmp_path / "worker.py"
    worker.write_text(WORKER)
    with installs(str(REPO)) as runs_of:
        layout = Path(runs_of[0].pythonpath)
        assert sorted(p.name for p in (layout / "qr_cl" / "kernels").glob("project.cl")) == ["project.cl"]
        assert (layout / "qr_cl" / "backbone" / "__init__.py").is_file()
        runs = ab_rounds(str(worker), runs_of, rounds=2, calls=3, describe=lambda run: run["qr_cl"],
                         worker_args=("--what", "x"))
    assert not layout.exists()                                       # removed when the block ends
    assert [len(runs["base"]), len(runs["this"])] == [2, 2]
    base, this = runs["base"][0], runs["this"][0]
    assert Path(base["qr_cl"]).is_relative_to(layout)
    assert Path(this["qr_cl"]).resolve() == (REPO / "qr_cl" / "__init__.py").resolve()   # an editable install
    assert base["argv"] == ["--worker", "-", "--calls", "3", "--what", "x"]
    assert not Path(base["cwd"]).resolve().is_relative_to(REPO)     # never the checkout: -m would import it
    assert capsys.readouterr().out.count("round ") == 4
