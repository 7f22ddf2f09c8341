"""The A/B harness: this checkout against another install of qr-cl, back to back, in fresh processes.

Every script that measures two installs names the other one ``--base PYTHON_OR_CHECKOUT``:

* the Python interpreter of an environment where the other qr-cl is installed (a venv of an
  earlier release, say), which runs it;
* or a checkout of qr-cl (a folder holding ``qr_cl/`` and ``setup.cfg``, e.g. a ``git worktree``
  of an earlier commit), laid out as its ``setup.cfg`` installs it (``package_dir`` folders, such as
  ``kernels/`` as ``qr_cl.kernels``) in a temporary folder and run by this interpreter, so that
  both share this environment's torch, pyopencl and numpy.

This checkout is the one this interpreter imports. Each run of an install is a fresh process
started in a temporary folder, not in a checkout (``python -m`` would import the working folder).
A script's own measurement runs under the hidden ``--worker INPUTS`` option, which
:func:`ab_parse` handles: it prints the measurement's JSON as the last line of the output.
"""
from __future__ import annotations

import argparse
import configparser
import json
import os
import shutil
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, Sequence

from benchutil import arguments

BASE_HELP = ("the other install: its Python interpreter, or a qr-cl checkout (run by this interpreter "
             "from a temporary copy laid out as installed)")


@dataclass(frozen=True)
class Install:
    """An install of qr-cl that runs in child processes: ``label`` ("base" or "this"), the
    interpreter ``python`` and, for a checkout, the folder ``pythonpath`` put before the
    interpreter's own packages."""
    label: str
    python: str
    pythonpath: str | None = None

    @property
    def env(self) -> dict[str, str] | None:
        """The child's environment: this one, with ``pythonpath`` first on PYTHONPATH (None: unchanged)."""
        if self.pythonpath is None:
            return None
        return {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, (self.pythonpath, os.environ.get("PYTHONPATH"))))}

    def command(self, args: Sequence[str]) -> list[str]:
        """The command line running ``python args`` in this install."""
        return [self.python, *args]

    def run(self, args: Sequence[str], **kwargs) -> subprocess.CompletedProcess:
        """``subprocess.run`` of ``python args`` in this install (keyword arguments passed on)."""
        return subprocess.run(self.command(args), env=self.env, **kwargs)

    def popen(self, args: Sequence[str], **kwargs) -> subprocess.Popen:
        """``subprocess.Popen`` of ``python args`` in this install (keyword arguments passed on)."""
        return subprocess.Popen(self.command(args), env=self.env, **kwargs)


THIS = Install("this", sys.executable)


def add_base_option(parser: argparse.ArgumentParser, required: bool) -> None:
    """Add ``--base PYTHON_OR_CHECKOUT`` (see the module's docstring)."""
    parser.add_argument("--base", metavar="PYTHON_OR_CHECKOUT", required=required, help=BASE_HELP)


def is_checkout(path: Path) -> bool:
    """Whether ``path`` is a qr-cl checkout: a folder holding ``qr_cl/__init__.py`` and ``setup.cfg``."""
    return (path / "qr_cl" / "__init__.py").is_file() and (path / "setup.cfg").is_file()


def lay_out_checkout(checkout: Path, target: Path) -> None:
    """Copy ``checkout``'s packages into ``target`` as its ``setup.cfg`` installs them: ``qr_cl/``
    and each ``package_dir`` folder at its package's place (``kernels/`` as ``qr_cl/kernels``)."""
    config = configparser.ConfigParser()
    config.read(checkout / "setup.cfg")
    mapping = {}
    for line in config.get("options", "package_dir", fallback="").splitlines():
        if "=" in line:
            package, folder = (part.strip() for part in line.split("=", 1))
            mapping[package] = folder
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(checkout / "qr_cl", target / "qr_cl", ignore=ignore)
    for package, folder in mapping.items():
        destination = target.joinpath(*package.split("."))
        shutil.rmtree(destination, ignore_errors=True)
        shutil.copytree(checkout / folder, destination, ignore=ignore)


@contextmanager
def installs(base: str | None) -> Iterator[list[Install]]:
    """``[base install, this]`` for the block (``[this]`` when ``base`` is None); a checkout is
    laid out in a temporary folder that the block's end removes. Exits with a one-line message
    when ``base`` is neither an interpreter nor a checkout."""
    if base is None:
        yield [THIS]
        return
    path = Path(base).expanduser()
    if path.is_dir():
        if not is_checkout(path):
            raise SystemExit(f"--base: {base}: a folder but not a qr-cl checkout (no qr_cl/__init__.py "
                             "and setup.cfg)")
        with tempfile.TemporaryDirectory(prefix="qr-cl-base-") as tmp:
            lay_out_checkout(path.resolve(), Path(tmp))
            yield [Install("base", sys.executable, tmp), THIS]
        return
    python = shutil.which(base)
    if python is None:
        raise SystemExit(f"--base: {base}: neither a Python interpreter nor a qr-cl checkout")
    yield [Install("base", python), THIS]


def ab_arguments(description: str, rounds: int, calls: int, base_required: bool = True,
                 calls_help: str = "timed calls per run, after a warm-up") -> argparse.ArgumentParser:
    """The options of a script timing installs against each other: ``--base``, ``--rounds``,
    ``--calls``, and the hidden ``--worker INPUTS`` under which it measures the install it runs
    in (see :func:`ab_rounds`). Without ``base_required`` the script may measure this checkout alone."""
    ap = argparse.ArgumentParser(description=description)
    add_base_option(ap, required=False)
    ap.add_argument("--rounds", type=arguments.positive_int, default=rounds,
                    help=f"runs of each install, alternating (default {rounds})")
    ap.add_argument("--calls", type=arguments.positive_int, default=calls, help=f"{calls_help} (default {calls})")
    ap.add_argument("--worker", help=argparse.SUPPRESS)      # inputs file ('-': none): measure, print JSON
    ap.set_defaults(base_required=base_required)
    return ap


def ab_parse(ap: argparse.ArgumentParser, measure: Callable[[argparse.Namespace], dict]) -> argparse.Namespace | None:
    """The parsed options of an :func:`ab_arguments` parser, ``inputs`` set to the worker's
    inputs file (None without one). Under ``--worker`` it prints the JSON of ``measure(args)``
    (the install this process imports) and returns None."""
    args = ap.parse_args()
    args.inputs = None if args.worker in (None, "-") else Path(args.worker)
    if args.worker is not None:
        print(json.dumps(measure(args)))
        return None
    if args.base_required and not args.base:
        ap.error("--base PYTHON_OR_CHECKOUT is required")
    return args


def ab_rounds(script: str, runs_of: list[Install], rounds: int, calls: int, describe: Callable[[dict], str],
              inputs: Path | None = None, worker_args: Sequence[str] = ()) -> dict[str, list[dict]]:
    """{label: [JSON of each run]}: ``script --worker inputs --calls calls *worker_args`` run
    ``rounds`` times under each install of ``runs_of`` alternately, each in a fresh process in a
    temporary folder. Prints each run as ``describe`` words it; exits with the tail of a failed
    run's stderr."""
    runs: dict[str, list[dict]] = {install.label: [] for install in runs_of}
    args = [str(Path(script).resolve()), "--worker", str(inputs.resolve()) if inputs else "-", "--calls", str(calls),
            *worker_args]
    with tempfile.TemporaryDirectory(prefix="qr-cl-ab-") as cwd:
        for r in range(rounds):
            for install in runs_of:
                proc = install.run(args, capture_output=True, text=True, cwd=cwd)
                if proc.returncode:
                    sys.exit(f"{install.label} run failed ({' '.join(install.command(args))}):\n{proc.stderr[-3000:]}")
                runs[install.label].append(json.loads(proc.stdout.strip().splitlines()[-1]))
                print(f"round {r + 1} {install.label}: {describe(runs[install.label][-1])}", flush=True)
    return runs
