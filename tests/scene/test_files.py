"""PLY / .splat I/O: real files, round trips, malformed input and hostile values."""
import struct
import warnings

import numpy as np
import pytest

import qr_cl
from qr_cl.runtime import SH_C0
from qr_cl.scene import Gaussians, SceneFormatError, ply_property_names, read_ply_vertices


def random_gaussians(n=50, degree=0, seed=0) -> Gaussians:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32),
                     (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                     np.exp(rng.uniform(-5, 0, (n, 3))).astype(np.float32),
                     rng.uniform(0.01, 0.99, n).astype(np.float32),
                     rng.normal(size=(n, (degree + 1) ** 2, 3)).astype(np.float32))


def write_ply(path, names, rows, fmt="binary_little_endian", types=None):
    types = types or ["float"] * len(names)
    header = ["ply", f"format {fmt} 1.0", f"element vertex {len(rows)}"]
    header += [f"property {t} {n}" for t, n in zip(types, names)] + ["end_header"]
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode())
        if fmt == "ascii":
            for r in rows:
                fh.write((" ".join(repr(float(v)) for v in r) + "\n").encode())
        else:
            fh.write(np.asarray(rows, "<f4").tobytes())


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("ascii", [False, True])
def test_round_trip_is_exact_to_float32(tmp_path, degree, ascii):
    g = random_gaussians(degree=degree, seed=degree)
    path = tmp_path / "g.ply"
    qr_cl.save_ply(path, g, ascii=ascii)
    h = qr_cl.load_ply(path)
    assert h.sh_degree == degree
    for field in ("means", "sh"):
        np.testing.assert_array_equal(getattr(h, field), getattr(g, field))
    for field in ("quats", "scales", "opacities"):  # activation(raw(x)) == x up to float32 rounding
        np.testing.assert_allclose(getattr(h, field), getattr(g, field), rtol=2e-6, atol=1e-7)
    qr_cl.save_ply(tmp_path / "again.ply", h, ascii=ascii)  # save(load(f)) reproduces the raw values
    first, _ = read_ply_vertices(path)
    again, _ = read_ply_vertices(tmp_path / "again.ply")
    assert list(first) == list(again) == ply_property_names(degree)
    for name in first:
        np.testing.assert_allclose(again[name], first[name], rtol=1e-5, atol=1e-6, err_msg=name)


def test_channel_major_f_rest_and_normals(tmp_path):
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(9)] + ["opacity", "scale_0", "scale_1", "scale_2",
                                                  "rot_0", "rot_1", "rot_2", "rot_3"]
    row = [1, 2, 3, 0, 0, 1, 0.1, 0.2, 0.3] + list(range(10, 19)) + [0.0, -1, -2, -3, 2, 0, 0, 0]
    write_ply(tmp_path / "n.ply", names, [row])
    g = qr_cl.load_ply(tmp_path / "n.ply")
    assert g.sh_degree == 1
    # f_rest_0..2 are R's coefficients 1..3, then G's, then B's
    np.testing.assert_array_equal(g.sh[0, 1:], [[10, 13, 16], [11, 14, 17], [12, 15, 18]])
    np.testing.assert_allclose(g.opacities, [0.5])
    np.testing.assert_allclose(g.scales[0], np.exp([-1, -2, -3]), rtol=1e-6)
    np.testing.assert_array_equal(g.quats[0], [1, 0, 0, 0])  # (2,0,0,0) normalised


def _good_rows(n=4):
    return [[0, 0, 0, 0.1, 0.2, 0.3, 0.0, -1, -1, -1, 1, 0, 0, 0]] * n


def test_truncated_body_names_file_and_counts(tmp_path):
    path = tmp_path / "t.ply"
    write_ply(path, ply_property_names(0), _good_rows(4))
    path.write_bytes(path.read_bytes()[:-30])
    with pytest.raises(SceneFormatError, match=r"t\.ply: truncated.*4 vertices.*3 complete"):
        qr_cl.load_ply(path)


def test_header_count_larger_than_ascii_data(tmp_path):
    path = tmp_path / "a.ply"
    write_ply(path, ply_property_names(0), _good_rows(2), fmt="ascii")
    path.write_bytes(path.read_bytes().replace(b"element vertex 2", b"element vertex 5"))
    with pytest.raises(SceneFormatError, match="declares 5 vertices.*2 lines"):
        qr_cl.load_ply(path)


def test_missing_property(tmp_path):
    names = [n for n in ply_property_names(0) if n != "opacity"]
    write_ply(tmp_path / "m.ply", names, [r[:6] + r[7:] for r in _good_rows(2)])
    with pytest.raises(SceneFormatError, match=r"m\.ply: missing vertex properties \['opacity'\]"):
        qr_cl.load_ply(tmp_path / "m.ply")


def test_non_float_type(tmp_path):
    names = ply_property_names(0)
    path = tmp_path / "i.ply"
    header = ["ply", "format binary_little_endian 1.0", "element vertex 1"]
    header += [f"property {'int' if n == 'scale_0' else 'float'} {n}" for n in names] + ["end_header"]
    path.write_bytes(("\n".join(header) + "\n").encode() + b"\0" * 4 * len(names))
    with pytest.raises(SceneFormatError, match=r"must be float32.*scale_0 \(int\)"):
        qr_cl.load_ply(path)


@pytest.mark.parametrize("content,match", [
    (b"hello\n", "not a PLY file"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n", "no 'end_header'"),
    (b"ply\nformat binary_big_endian 1.0\nelement face 2\nend_header\n", "before 'vertex'"),
    (b"ply\nformat xml 1.0\nelement vertex 1\nend_header\n", "unsupported PLY format"),
])
def test_malformed_headers(tmp_path, content, match):
    (tmp_path / "bad.ply").write_bytes(content)
    with pytest.raises(SceneFormatError, match=match):
        qr_cl.load_ply(tmp_path / "bad.ply")


def test_missing_file():
    with pytest.raises(SceneFormatError, match="no such file"):
        qr_cl.load_ply("/nonexistent/scene.ply")


def test_hostile_values_are_repaired_with_warnings(tmp_path):
    rows = np.array(_good_rows(6), np.float32)
    rows[0, 6] = np.inf                 # opacity logit +inf
    rows[1, 6] = -np.inf
    rows[2, 0] = np.nan                 # NaN position: dropped
    rows[3, 10:14] = 0                  # zero quaternion
    rows[4, 10:14] = [2, 0, 0, 0]       # non-unit quaternion
    write_ply(tmp_path / "h.ply", ply_property_names(0), rows)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        g = qr_cl.load_ply(tmp_path / "h.ply")
    text = " | ".join(str(w.message) for w in caught)
    assert "dropped 1 of 6" in text and "clamped 2 infinite opacity" in text
    assert "1 zero quaternions" in text and "normalised" in text
    assert len(g) == 5
    np.testing.assert_allclose(g.opacities[:2], [1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(g.quats, axis=1), 1, rtol=1e-6)
    assert np.isfinite(g.means).all()


def test_huge_log_scales_are_clamped_with_a_warning(tmp_path):
    rows = np.array(_good_rows(3), np.float32)
    rows[1, 7:10] = [95.0, 0.0, 1e30]     # exp overflows float32
    write_ply(tmp_path / "big.ply", ply_property_names(0), rows)
    with pytest.warns(UserWarning, match="clamped 1 Gaussians' log-scales"):
        g = qr_cl.load_ply(tmp_path / "big.ply")
    assert len(g) == 3 and np.isfinite(g.scales).all() and g.scales[1].max() > 1e30


def test_splat_reader(tmp_path):
    rec = struct.pack("<3f3f4B4B", 1, 2, 3, 0.1, 0.2, 0.3, 255, 128, 0, 128, 255, 128, 128, 128)
    (tmp_path / "s.splat").write_bytes(rec * 3)
    g = qr_cl.load_splat(tmp_path / "s.splat")
    assert len(g) == 3 and g.sh_degree == 0
    np.testing.assert_allclose(g.rgb[0], [1, 128 / 255, 0], atol=1e-6)
    np.testing.assert_allclose(g.scales[0], [0.1, 0.2, 0.3], rtol=1e-6)
    np.testing.assert_allclose(g.opacities[0], 128 / 255, rtol=1e-6)
    np.testing.assert_allclose(g.quats[0], [1, 0, 0, 0])
    (tmp_path / "bad.splat").write_bytes(rec + b"\0" * 5)
    with pytest.raises(SceneFormatError, match="not a multiple of the 32-byte"):
        qr_cl.load_scene(tmp_path / "bad.splat")


def test_real_scenes_load(shared_data):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        fox = qr_cl.load_ply(shared_data / "wakufactory-fox" / "fox.ply")
    assert len(fox) == 50000 and fox.sh_degree == 0
    assert any("clamped 37 infinite opacity" in str(w.message) for w in caught)
    assert np.isfinite(fox.opacities).all() and fox.opacities.max() == 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        donut = qr_cl.load_ply(shared_data / "v3dg-donut" / "donut_fused.ply")
    assert len(donut) == 45624
    np.testing.assert_allclose(np.linalg.norm(donut.quats, axis=1), 1, rtol=1e-5)
    assert abs(SH_C0 * donut.sh[:, 0].max() + 0.5 - (SH_C0 * 14.86 + 0.5)) < 0.01
