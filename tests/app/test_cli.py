"""The qr-cl command line: demo, render, devices, errors."""
import numpy as np
from matplotlib.image import imread

from qr_cl.app.cli import main
from qr_cl.app.scenes.procedural import procedural_scene
from qr_cl.scene import save_ply


def test_render_orbit_of_a_saved_scene(tmp_path, capsys):
    save_ply(tmp_path / "scene.ply", procedural_scene(1000))
    out = tmp_path / "r"
    assert main(["render", str(tmp_path / "scene.ply"), "--orbit", "2", "--width", "64",
                 "--height", "48", "--out", str(out)]) == 0
    assert "rendered 2 views" in capsys.readouterr().out
    rgb = imread(out / "001_rgb.png")
    alpha = imread(out / "001_alpha.png")[..., 0]
    assert rgb.shape[:2] == (48, 64) and rgb[..., :3].std() > 0.05
    assert 0.05 < (alpha > 0.5).mean() < 0.95
    assert (out / "000_depth.png").is_file()


def test_render_bad_file_is_a_one_line_error(tmp_path, capsys):
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n")
    assert main(["render", str(tmp_path / "bad.ply"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("qr-cl: error:") and "bad.ply" in err and "Traceback" not in err


def test_a_render_the_memory_cannot_hold_is_a_one_line_error(tmp_path, capsys, monkeypatch):
    from qr_cl.runtime import host_memory, host_pool
    save_ply(tmp_path / "scene.ply", procedural_scene(1000))
    monkeypatch.setattr(host_memory, "HOST_CHECK_BYTES", 1 << 10)
    monkeypatch.setattr(host_memory, "available_host_bytes", lambda: 2048)
    host_pool().clear()
    assert main(["render", str(tmp_path / "scene.ply"), "--orbit", "1", "--width", "64", "--height", "48",
                 "--out", str(tmp_path / "r")]) == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]          # after the progress bar
    assert last.startswith("qr-cl: error: a ") and "GB of host memory" in last and "0.00 GB available" in last
    assert "Traceback" not in capsys.readouterr().err


def test_devices_marks_the_chosen_one(capsys):
    assert main(["devices"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert sum(line.startswith("*") for line in lines) == 2  # the device line and the legend


def test_donut_renders_recognizably(shared_data, tmp_path):
    """The real donut from its own camera: a centred object covering a good part of the frame."""
    layout = shared_data / "v3dg-donut" / "_SingleDonut.json"
    assert main(["render", str(shared_data / "v3dg-donut" / "donut_fused.ply"), "--cameras", str(layout),
                 "--width", "480", "--out", str(tmp_path)]) == 0
    alpha = imread(tmp_path / "000_alpha.png")[..., 0]
    rgb = imread(tmp_path / "000_rgb.png")[..., :3]
    assert alpha.shape == (270, 480)
    ys, xs = np.nonzero(alpha > 0.5)
    assert 0.1 < (alpha > 0.5).mean() < 0.6
    assert abs(xs.mean() - 240) < 40 and abs(ys.mean() - 135) < 60
    pink = (rgb[..., 0] > 0.7) & (rgb[..., 2] > 0.6) & (rgb[..., 1] < 0.75)  # frosting
    assert pink.sum() > 0.05 * len(xs)


def test_bad_input_gets_a_message_not_a_traceback(tmp_path, capsys):
    """As a new user would meet them: a missing or foreign checkpoint, a missing --data folder or
    report: exit 2 and one line naming the file and what is wrong."""
    garbage = tmp_path / "garbage.pt"
    garbage.write_text("not a checkpoint")
    cases = [(["eval", str(tmp_path), "--checkpoint", str(tmp_path / "none.pt"), "--out", str(tmp_path / "e")],
              "none.pt: no such checkpoint file"),
             (["eval", str(tmp_path), "--checkpoint", str(garbage), "--out", str(tmp_path / "e")],
              "garbage.pt: not a torch checkpoint"),
             (["reproduce", "--quick", "--data", str(tmp_path / "nodata"), "--out", str(tmp_path / "r")],
              "nodata: no such folder (--data)"),
             (["bench", "compare", str(tmp_path / "a.json"), str(tmp_path / "b.json")], "a.json: No such file")]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("qr-cl: error: ") and message in err and "Traceback" not in err, (argv, err)
