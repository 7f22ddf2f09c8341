"""``qr-cl query``: relevancy as LERF/LangSplat define it, text lookup (scene classes, the shipped
CLIP table, an encoder), the optional open_clip path with a stub module, and the command on a
small trained checkpoint (relevancy highest on the queried class's Gaussians), bad input."""
from __future__ import annotations

import json
import os
import sys
import types
import zlib

import numpy as np
import pytest
import torch
from matplotlib.image import imread

from qr_cl.app.cli import build_parser, main
from qr_cl.app.query import command
from qr_cl.app.query.relevancy import CANONICAL_PHRASES, negatives, relevancy
from qr_cl.app.query.scene import read_features
from qr_cl.app.query.text import (ENCODER, SCENE_CLASSES, SHIPPED_TABLE, QueryError, TextLookup,
                                  UnknownQueryError, open_clip_encoder)
from qr_cl.app.scenes.folders import ClassTable, SceneDataError, load_scene_folder, unit_rows
from qr_cl.app.scenes.room_features import RoomFeatures
from qr_cl.app.vocab import scannet200
from qr_cl.scene import load_ply
from tests.app.query_helpers import tiny_checkpoint, top_purity
from tests.synthetic_helpers import tiny_config


def _table_rows(*names):
    known, table = scannet200()
    return table[[known.index(n) for n in names]]


class StubEncoder:
    """A text encoder for tests: fixed texts map to given rows (scaled: the lookup normalises),
    anything else to a random row seeded by the text; it records what it was asked."""

    def __init__(self, rows: dict[str, np.ndarray], dim: int):
        self.rows, self.dim, self.asked = rows, dim, []

    def __call__(self, texts):
        self.asked += list(texts)
        return np.stack([self.rows[t] * 3 if t in self.rows else
                         np.random.default_rng(zlib.crc32(t.encode())).standard_normal(self.dim) for t in texts])


def test_relevancy_is_the_minimum_pairwise_softmax():
    rng = np.random.default_rng(0)
    f, q = unit_rows(rng.standard_normal((50, 16))), unit_rows(rng.standard_normal(16))
    neg = unit_rows(rng.standard_normal((4, 16)))
    s_q, s_n = f @ q, f @ neg.T
    pairwise = np.exp(s_q[:, None] / 0.1) / (np.exp(s_q[:, None] / 0.1) + np.exp(s_n / 0.1))
    assert np.allclose(relevancy(f, q, neg), pairwise.min(1), atol=1e-6)
    assert np.allclose(relevancy(f, q, neg[:0]), 1 / (1 + np.exp(-s_q / 0.1)), atol=1e-6)
    assert 0 <= relevancy(f, q, neg).min() and relevancy(f, q, neg).max() <= 1


def test_lookup_order_aliases_and_near_matches():
    classes = ClassTable(np.array([1, 6, 5]), ["Wall", "sofa", "chair"], _table_rows("wall", "couch", "chair"))
    lookup = TextLookup(512, classes)
    wall = lookup("  WALL ")
    assert wall.source == SCENE_CLASSES and np.allclose(wall.embedding, classes.text_features[0])
    assert lookup("couch").source == SCENE_CLASSES                      # the table's name of the scene's sofa
    office = lookup("office chair")
    assert office.source == SHIPPED_TABLE and np.allclose(office.embedding, _table_rows("office chair")[0])
    with pytest.raises(UnknownQueryError, match="closest: chair") as err:
        lookup("chiar")
    assert "--clip-weights" in str(err.value)
    with pytest.raises(QueryError, match="empty"):
        lookup("  ")
    simulated = ClassTable(classes.ids, classes.names, unit_rows(np.random.default_rng(0).standard_normal((3, 512))))
    with pytest.raises(UnknownQueryError):                           # simulated text: the table does not apply
        TextLookup(512, simulated)("office chair")
    with pytest.raises(UnknownQueryError):
        TextLookup(32)("office chair")                               # 32-D features: neither does it
    assert TextLookup(512)("sofa").source == SHIPPED_TABLE           # no classes.json: the table, by its alias


def test_encoder_texts_and_negatives():
    dim = 8
    seat = unit_rows(np.arange(1, dim + 1, dtype=np.float32))
    encoder = StubEncoder({"something to sit on": seat}, dim)
    classes = ClassTable(np.array([1, 2]), ["wall", "floor"], unit_rows(np.eye(dim)[:2]))
    lookup = TextLookup(dim, classes, encoder)
    got = lookup("something to sit on")
    assert got.source == ENCODER and np.allclose(got.embedding, seat, atol=1e-6)
    assert lookup("wall").source == SCENE_CLASSES                    # known names never reach the encoder
    assert encoder.asked == ["something to sit on"]
    neg = negatives(lookup, got)
    assert encoder.asked[-4:] == list(CANONICAL_PHRASES) and neg.shape == (4, dim)
    plain = TextLookup(dim, classes)
    assert np.allclose(negatives(plain, plain("wall")), classes.text_features[1:])   # the other classes
    wrong = TextLookup(dim, classes, StubEncoder({}, dim + 1))
    with pytest.raises(QueryError, match="8-D"):
        wrong("anything")


def test_open_clip_path_with_a_stub_module(tmp_path, monkeypatch):
    calls = {}

    class Net:
        def eval(self):
            calls["eval"] = True

        def encode_text(self, tokens):
            return torch.tensor(tokens, dtype=torch.float32) * 2

    stub = types.ModuleType("open_clip")
    stub.create_model = lambda model, pretrained: calls.update(model=model, pretrained=pretrained) or Net()
    stub.get_tokenizer = lambda model: lambda texts: [[len(t), 1.0, 0.0] for t in texts]
    monkeypatch.setitem(sys.modules, "open_clip", stub)
    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    with pytest.raises(QueryError, match="no such CLIP weights file"):
        open_clip_encoder(tmp_path / "missing.bin")
    weights = tmp_path / "vit.bin"
    weights.write_bytes(b"x")
    encode = open_clip_encoder(weights, "ViT-B-16")
    assert calls == {"model": "ViT-B-16", "pretrained": str(weights), "eval": True}
    assert os.environ["HF_HUB_OFFLINE"] == "1"
    assert np.allclose(encode(["ab", "abc"]), [[4, 2, 0], [6, 2, 0]])
    monkeypatch.setitem(sys.modules, "open_clip", None)               # not installed
    with pytest.raises(QueryError, match=r"qr-cl\[clip\]"):
        open_clip_encoder(weights)


def test_feature_files(tmp_path):
    feats = np.random.default_rng(0).standard_normal((5, 3)).astype(np.float32)
    props = "".join(f"property float feature_{i}\n" for i in (2, 0, 1))
    with open(tmp_path / "f.ply", "wb") as fh:
        fh.write(f"ply\nformat binary_little_endian 1.0\nelement vertex 5\n{props}end_header\n".encode())
        fh.write(np.ascontiguousarray(feats[:, [2, 0, 1]]).tobytes())
    assert np.array_equal(read_features(tmp_path / "f.ply", 5), feats)
    np.save(tmp_path / "f.npy", feats)
    assert np.array_equal(read_features(tmp_path / "f.npy", 5), feats)
    with pytest.raises(SceneDataError, match=r"f\.npy.*the scene has 6 Gaussians"):
        read_features(tmp_path / "f.npy", 6)


@pytest.fixture(scope="module")
def checkpoint(tiny_room, tmp_path_factory):
    return tiny_checkpoint(tiny_room, tmp_path_factory.mktemp("gsnet"))


def test_query_command_on_a_trained_checkpoint(tiny_room, checkpoint, tmp_path, capsys):
    out = tmp_path / "q"
    assert main(["query", str(tiny_room), "wall", "Floor", "chair", "--checkpoint", str(checkpoint),
                 "--out", str(out), "--threshold", "0.5", "--views", "0", "2"]) == 0
    assert "'wall' (classes.json)" in capsys.readouterr().out
    data = load_scene_folder(tiny_room)
    labels, ids = data.gaussian_labels, dict(zip(data.classes.names, data.classes.ids.tolist()))
    summary = json.loads((out / "query.json").read_text())["queries"]
    for name in ("wall", "floor", "chair"):
        values = np.load(out / f"{name}.npy")
        assert values.shape == (len(labels),) and 0 <= values.min() and values.max() <= 1
        inside = labels == ids[name]
        assert values[inside].mean() > 3 * values[~inside].mean(), name
        assert top_purity(values, labels, ids[name]) > (0.6 if name != "chair" else 0.4), name
        ply = load_ply(out / f"{name}.ply")
        assert len(ply) == len(labels)
        assert ply.rgb[values.argmax(), 0] > ply.rgb[values.argmin(), 0]        # turbo: hot is red
        assert len(load_ply(out / f"{name}_selected.ply")) == (values >= 0.5).sum() == summary[name]["selected"]
    for name in ("wall", "floor"):                                            # the ">60 % of the top decile" criterion
        assert top_purity(np.load(out / f"{name}.npy"), labels, ids[name], 0.1) > 0.6, name
    cam = data.frames[2].camera
    rgb, wall, floor = (imread(out / "views" / f"002_{n}.png")[..., :3] for n in ("rgb", "wall", "floor"))
    assert rgb.shape == wall.shape == (cam.height, cam.width, 3)
    assert np.abs(wall - floor).mean() > 0.05 and np.abs(wall - rgb).mean() > 0.05


def test_query_through_an_encoder_and_a_features_file(tiny_room, tmp_path):
    data = load_scene_folder(tiny_room)
    protos = RoomFeatures(tiny_config()).text()
    np.save(tmp_path / "f.npy", np.stack([protos[max(int(c), 1)] for c in data.gaussian_labels]).astype(np.float32))
    toilet = data.classes.names.index("toilet")
    encoder = StubEncoder({"where one washes": data.classes.text_features[toilet]}, tiny_config().dim)
    args = build_parser().parse_args(["query", str(tiny_room), "where one washes", "--features",
                                      str(tmp_path / "f.npy"), "--out", str(tmp_path / "q"), "--orbit", "1",
                                      "--width", "64", "--score", "cosine"])
    assert command.run(args, encoder=encoder) == 0
    summary = json.loads((tmp_path / "q" / "query.json").read_text())["queries"]["where_one_washes"]
    assert summary["source"] == ENCODER and summary["score"] == "cosine"
    values = np.load(tmp_path / "q" / "where_one_washes.npy")
    assert top_purity(values, data.gaussian_labels, int(data.classes.ids[toilet])) > 0.9
    assert (tmp_path / "q" / "views" / "orbit000_where_one_washes.png").is_file()


def test_bad_query_input_is_one_line(tiny_room, checkpoint, tmp_path, capsys):
    base = ["query", str(tiny_room), "--out", str(tmp_path / "q")]
    cases = [(base + ["chiar", "--checkpoint", str(checkpoint)], "unknown query 'chiar'"),
             (base + ["wall", "--checkpoint", str(tmp_path / "none.pt")], "none.pt: no such checkpoint file"),
             (base + ["wall", "--features", str(tmp_path / "none.npy")], "none.npy: no such features file"),
             (base + ["wall", "--checkpoint", str(checkpoint), "--views", "99"], "--views [99]")]
    for argv, message in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith("qr-cl: error: ") and message in err and err.count("\n") == 1, (argv, err)
    assert not (tmp_path / "q").exists()                                 # refused before writing anything


def test_network_features_in_half_render_as_their_float_values(tiny_room, checkpoint):
    """GS-Net's output kept as float16 for rendering: its float32 values rounded, rendered as the
    float32 table of those values."""
    import qr_cl
    from qr_cl.app.training.network import network_features
    data = load_scene_folder(tiny_room)
    full = network_features(checkpoint, data)
    half = network_features(checkpoint, data, np.float16)
    assert half.dtype == np.float16 and np.array_equal(half, full.astype(np.float16))
    g, cam = data.gaussians, data.frames[0].camera
    images = [qr_cl.rasterize(g.means, g.quats, g.scales, g.opacities, table, cam.viewmat, cam.K, cam.width,
                              cam.height, sampler="quantile", k=20)[0] for table in (half, half.astype(np.float32))]
    assert images[0].numpy().tobytes() == images[1].numpy().tobytes()
