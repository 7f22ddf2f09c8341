"""Every ``qr-cl`` command checks its sizes, counts and steps where it parses them: a zero or
negative one is a one-line error with exit status 2, never a traceback."""
import argparse

import pytest

from qr_cl.app import arguments
from qr_cl.app.cli import DELEGATED, main
from qr_cl.app.training import command as train_command

# (argv, the option whose value is refused): one per command, every subcommand of qr-cl but devices
# and convert (which take no size, count or step) and bench's (compare, sweep, implementations: none)
BAD = [(["render", "scene.ply", "--orbit", "2", "--width", "-5", "--out", "o"], "--width"),
       (["render", "scene.ply", "--orbit", "0", "--out", "o"], "--orbit"),
       (["train", "room", "--out", "o", "--steps", "0"], "--steps"),
       (["train", "room", "--out", "o", "--grid-size", "-0.1"], "--grid-size"),
       (["eval", "room", "--features", "f.npy", "--out", "o", "--knn", "0"], "--knn"),
       (["reproduce", "--seed", "-1"], "--seed"),
       (["demo", "--steps", "0"], "--steps"),
       (["demo", "--rays", "-2048"], "--rays"),
       (["bench", "scale", "0"], "N"),
       (["register", "room", "--out", "o", "-k", "0"], "-k"),
       (["query", "room", "chair", "--features", "f.npy", "--width", "-5"], "--width"),
       (["query", "room", "chair", "--features", "f.npy", "--orbit", "0"], "--orbit"),
       (["view", "room", "--height", "0"], "--height"),
       (["view", "room", "--port", "-1"], "--port"),
       (["features", "room", "--images", "i", "--clip-weights", "c", "--sam-weights", "s", "--batch", "0"],
        "--batch")]


def _one_line_error(capsys, call) -> str:
    with pytest.raises(SystemExit) as exit_:
        call()
    assert exit_.value.code == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "Traceback" not in captured.err
    assert captured.err.count("\n") == 1, captured.err
    return captured.err


@pytest.mark.parametrize("argv, option", BAD, ids=[" ".join(argv[:1] + argv[-2:]) for argv, _ in BAD])
def test_a_zero_or_negative_size_is_a_one_line_error(argv, option, capsys):
    err = _one_line_error(capsys, lambda: main(argv))
    prog = f"qr-cl {argv[0]}" + (f" {argv[1]}" if argv[0] == "bench" else "")
    assert err.startswith(f"{prog}: error: argument {option}") and "expected" in err, err


def test_every_command_is_tried():
    assert {argv[0] for argv, _ in BAD} == set(DELEGATED) - {"devices", "convert"}


def test_the_torchrun_entry_of_train_checks_too(capsys):
    err = _one_line_error(capsys, lambda: train_command.main(["room", "--out", "o", "--views", "0"]))
    assert err.startswith("python -m qr_cl.app.training.command: error: argument --views: expected a positive")


def test_register_refuses_a_level_it_does_not_have(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["register", "room", "--out", "o", "--levels", "-1"])
    assert "--levels takes levels of 0 1 2 3" in str(exit_.value) and "\n" not in str(exit_.value)


@pytest.mark.parametrize("check, good, bad", [
    (arguments.positive_int, {"1": 1, "640": 640}, ["0", "-5", "1.5", "x", ""]),
    (arguments.nonnegative_int, {"0": 0, "7": 7}, ["-1", "two"]),
    (arguments.positive_float, {"0.1": 0.1, "2": 2.0}, ["0", "-0.1", "nan", "inf", "x"]),
    (arguments.port_number, {"0": 0, "8000": 8000, "65535": 65535}, ["-1", "65536"])])
def test_the_checks(check, good, bad):
    for text, value in good.items():
        assert check(text) == value
    for text in bad:
        with pytest.raises(argparse.ArgumentTypeError, match="expected"):
            check(text)
