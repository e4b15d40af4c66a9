"""DINOv2 run as its authors run it, and SALAD, BoQ and MegaLoc read from files written in their
published layouts (the keys and shapes of the authors' code, random values): each descriptor
equals the published model's forward computed here from the raw tensors of the file."""

import math

import helpers
import numpy as np
import pytest
import torch
import torch.nn.functional as F
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from torch import nn

from locretrieval.models.trainable.dinov2 import DinoV2Trunk, dinov2_position_embedding, salad_columns

QUIET = ("device=cpu", "model.extraction.num_workers=0", "model.extraction.progress=false")
#: Images whose sides are multiples of 14: a 9 x 11 patch grid (more patches than SALAD's 64 clusters).
IMAGES = torch.rand(2, 3, 126, 154, generator=torch.Generator().manual_seed(0))


def bicubic_numpy(grid: np.ndarray, out_rows: int, out_cols: int, scale_rows: float, scale_cols: float) -> np.ndarray:
    """Keys' cubic convolution (a = -0.75) of a ``[rows, cols, C]`` grid, sampled at
    ``(i + 0.5) / scale - 0.5`` along each axis, the border repeated."""
    a = -0.75

    def weights(t):
        near = lambda x: ((a + 2) * x - (a + 3)) * x * x + 1  # noqa: E731  |x| <= 1
        far = lambda x: ((a * x - 5 * a) * x + 8 * a) * x - 4 * a  # noqa: E731  1 < |x| < 2
        return [far(t + 1), near(t), near(1 - t), far(2 - t)]

    def along(values, size, scale):
        source = (np.arange(size) + 0.5) / scale - 0.5
        first = np.floor(source).astype(int)
        taps = weights(source - first)
        rows = [values[np.clip(first - 1 + k, 0, len(values) - 1)] for k in range(4)]
        return sum(w.reshape(-1, *[1] * (values.ndim - 1)) * r for w, r in zip(taps, rows))

    resized = along(grid, out_rows, scale_rows)
    return np.swapaxes(along(np.swapaxes(resized, 0, 1), out_cols, scale_cols), 0, 1)


def test_the_position_grid_is_resized_as_dinov2_does_by_scale_factor_with_its_offset():
    from timm.layers import resample_abs_pos_embed

    embedding = torch.randn(1, 1 + 37 * 37, 4, generator=torch.Generator().manual_seed(1))
    grid = embedding[0, 1:].reshape(37, 37, 4).numpy().astype(np.float64)
    ours = dinov2_position_embedding(embedding, 9, 11)
    expected = bicubic_numpy(grid, 9, 11, 9.1 / 37, 11.1 / 37).reshape(99, 4)
    np.testing.assert_allclose(ours[0, 1:].numpy(), expected, atol=1e-5)
    torch.testing.assert_close(ours[:, :1], embedding[:, :1])  # the class position is kept
    # without the offset it is timm's resampling to the size without antialiasing (the offset changes the values)
    plain = resample_abs_pos_embed(embedding, new_size=(9, 11), num_prefix_tokens=1, antialias=False)
    torch.testing.assert_close(dinov2_position_embedding(embedding, 9, 11, offset=0.0), plain)
    assert not torch.allclose(ours, plain, atol=1e-3)
    assert dinov2_position_embedding(embedding, 37, 37) is embedding  # the stored grid, as DINOv2 returns it


def test_the_trunk_equals_timm_at_the_stored_grid_and_refuses_sides_that_are_not_patch_multiples():
    trunk = DinoV2Trunk("vit_small_patch14_dinov2", class_token=True).eval()
    images = torch.rand(1, 3, 518, 518)
    with torch.no_grad():
        feature_map, class_token = trunk(images)
        tokens = trunk.timm.forward_features(images)  # timm's own forward: 37 x 37 patches, nothing resampled
    torch.testing.assert_close(feature_map.flatten(2).transpose(1, 2), tokens[:, 1:])
    torch.testing.assert_close(class_token, tokens[:, 0])
    before_norm = DinoV2Trunk("vit_small_patch14_dinov2", final_norm=False).eval()
    before_norm.load_state_dict(trunk.state_dict())
    with torch.no_grad():
        unnormed = before_norm(images)
    torch.testing.assert_close(trunk.timm.norm(unnormed.flatten(2).transpose(1, 2)), tokens[:, 1:])
    with pytest.raises(ValueError, match="multiples of 14 px, got 100 x 126"):
        trunk(torch.rand(1, 3, 126, 100))


@pytest.fixture(scope="module")
def dinov2_base():
    """DINOv2 ViT-B/14 keys and shapes (timm's names are DINOv2's) with random values, and its mask token."""
    import timm

    torch.manual_seed(0)
    state = timm.create_model("vit_base_patch14_dinov2", pretrained=False, num_classes=0).state_dict()
    return {**state, "mask_token": torch.randn(1, 768) * 0.02}


def random_tensors(shapes: dict[str, tuple[int, ...]], seed: int) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    tensors = {}
    for key, shape in shapes.items():
        values = torch.randn(shape, generator=generator)
        tensors[key] = 1 + 0.1 * values if ("norm" in key and key.endswith("weight")) else 0.05 * values
    return tensors


def salad_shapes(prefix: str, clusters: int, cluster_dim: int, token_dim: int, channels: int = 768, hidden: int = 512):
    """SALAD's aggregator as its code registers it (dropout at index 1 of the convolution branches)."""
    return {
        f"{prefix}token_features.0.weight": (hidden, channels),
        f"{prefix}token_features.0.bias": (hidden,),
        f"{prefix}token_features.2.weight": (token_dim, hidden),
        f"{prefix}token_features.2.bias": (token_dim,),
        f"{prefix}cluster_features.0.weight": (hidden, channels, 1, 1),
        f"{prefix}cluster_features.0.bias": (hidden,),
        f"{prefix}cluster_features.3.weight": (cluster_dim, hidden, 1, 1),
        f"{prefix}cluster_features.3.bias": (cluster_dim,),
        f"{prefix}score.0.weight": (hidden, channels, 1, 1),
        f"{prefix}score.0.bias": (hidden,),
        f"{prefix}score.3.weight": (clusters, hidden, 1, 1),
        f"{prefix}score.3.bias": (clusters,),
        f"{prefix}dust_bin": (),
    }


def published_trunk(state: dict, prefix: str, final_norm: bool = True) -> DinoV2Trunk:
    """The DINOv2 trunk filled, by name, with the file's backbone tensors (mask token left out)."""
    trunk = DinoV2Trunk("vit_base_patch14_dinov2", class_token=True, final_norm=final_norm).eval()
    trunk.timm.load_state_dict(
        {k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix) and "mask_token" not in k}
    )
    return trunk


def published_salad(state: dict, prefix: str, feature_map: torch.Tensor, class_token: torch.Tensor) -> torch.Tensor:
    """SALAD's forward as published: 1 x 1 convolutions, SuperGlue's log-domain optimal transport
    (3 iterations) with the dustbin, assigned features summed per cluster ``[B, cluster_dim, clusters]``,
    each cluster L2-normalised, flattened dimension-major after the normalised token, then L2."""

    def branch(name, x):
        hidden = F.relu(F.conv2d(x, state[f"{prefix}{name}.0.weight"], state[f"{prefix}{name}.0.bias"]))
        return F.conv2d(hidden, state[f"{prefix}{name}.3.weight"], state[f"{prefix}{name}.3.bias"])

    features, scores = branch("cluster_features", feature_map).flatten(2), branch("score", feature_map).flatten(2)
    hidden = F.relu(
        F.linear(class_token, state[f"{prefix}token_features.0.weight"], state[f"{prefix}token_features.0.bias"])
    )
    token = F.linear(hidden, state[f"{prefix}token_features.2.weight"], state[f"{prefix}token_features.2.bias"])
    batch, m, n = scores.shape
    couplings = torch.cat([scores, state[f"{prefix}dust_bin"].expand(batch, 1, n)], dim=1)
    norm = -math.log(m + n)
    log_mu = torch.cat([torch.full((m,), norm), torch.tensor([math.log(n - m) + norm])])
    log_nu = torch.full((n,), norm)
    u, v = torch.zeros(batch, m + 1), torch.zeros(batch, n)
    for _ in range(3):
        u = log_mu - torch.logsumexp(couplings + v[:, None, :], dim=2)
        v = log_nu - torch.logsumexp(couplings + u[:, :, None], dim=1)
    plan = (couplings + u[:, :, None] + v[:, None, :] - norm).exp()[:, :-1]
    aggregated = (features[:, :, None, :] * plan[:, None, :, :]).sum(dim=-1)
    descriptor = torch.cat([F.normalize(token, dim=-1), F.normalize(aggregated, dim=1).flatten(1)], dim=-1)
    return F.normalize(descriptor, dim=-1)


def load_model(config: str, weights, *overrides):
    return instantiate(helpers.evaluate_config(f"model={config}", f"model.weights={weights}", *overrides, *QUIET).model)


def test_salad_reads_its_published_file_and_gives_the_published_descriptor_reordered(dinov2_base, tmp_path):
    state = {f"backbone.model.{k}": v for k, v in dinov2_base.items()}
    state.update(random_tensors(salad_shapes("aggregator.", 64, 128, 256), seed=1))
    torch.save(state, tmp_path / "dino_salad.ckpt")
    model = load_model("dinov2_salad", tmp_path / "dino_salad.ckpt")
    assert not model.weights.random_init and model.network.output_dim == 8448
    with torch.no_grad():
        ours = model.network.eval()(IMAGES)
        expected = published_salad(state, "aggregator.", *published_trunk(state, "backbone.model.")(IMAGES))
    torch.testing.assert_close(ours, expected[:, salad_columns(64, 128, 256)], atol=2e-5, rtol=1e-4)
    torch.testing.assert_close(ours @ ours.T, expected @ expected.T, atol=2e-5, rtol=1e-4)  # the same similarities


@pytest.mark.slow
def test_megaloc_reads_its_published_file_and_gives_the_published_descriptor(dinov2_base, tmp_path):
    # the head's tensors (the linear layer's 140 M values) drawn once: both layouts hold the same values
    head = random_tensors(salad_shapes("aggregator.agg.", 64, 256, 256), seed=2)
    head.update(random_tensors({"aggregator.linear.weight": (8448, 16640), "aggregator.linear.bias": (8448,)}, seed=3))
    published = None
    for backbone_prefix in ("backbone.model.", "backbone."):  # the GitHub release, and the later DINOv2-only layout
        state = {f"{backbone_prefix}{k}": v for k, v in dinov2_base.items()} | head
        torch.save(state, tmp_path / "megaloc.torch")
        model = load_model("dinov2_megaloc", tmp_path / "megaloc.torch")
        with torch.no_grad():
            ours = model.network.eval()(IMAGES)
            if published is None:  # the published forward of these values, from the first file's tensors
                salad = published_salad(state, "aggregator.agg.", *published_trunk(state, backbone_prefix)(IMAGES))
                linear = F.linear(salad, state["aggregator.linear.weight"], state["aggregator.linear.bias"])
                published = F.normalize(linear, dim=-1)
        torch.testing.assert_close(ours, published, atol=2e-5, rtol=1e-4)


def boq_shapes(channels=768, dim=384, queries=64, blocks=2, rows=32) -> dict[str, tuple[int, ...]]:
    """BoQ's aggregator as its code registers it (``proj_c`` a 3 x 3 convolution)."""
    shapes = {
        "aggregator.proj_c.weight": (dim, channels, 3, 3),
        "aggregator.proj_c.bias": (dim,),
        "aggregator.norm_input.weight": (dim,),
        "aggregator.norm_input.bias": (dim,),
        "aggregator.fc.weight": (rows, blocks * queries),
        "aggregator.fc.bias": (rows,),
    }
    for i in range(blocks):
        block = f"aggregator.boqs.{i}."
        shapes[f"{block}queries"] = (1, queries, dim)
        for attention in ("encoder.self_attn.", "self_attn.", "cross_attn."):
            shapes.update(
                {
                    f"{block}{attention}in_proj_weight": (3 * dim, dim),
                    f"{block}{attention}in_proj_bias": (3 * dim,),
                    f"{block}{attention}out_proj.weight": (dim, dim),
                    f"{block}{attention}out_proj.bias": (dim,),
                }
            )
        for norm in ("encoder.norm1.", "encoder.norm2.", "norm_q.", "norm_out."):
            shapes.update({f"{block}{norm}weight": (dim,), f"{block}{norm}bias": (dim,)})
        shapes.update(
            {
                f"{block}encoder.linear1.weight": (4 * dim, dim),
                f"{block}encoder.linear1.bias": (4 * dim,),
                f"{block}encoder.linear2.weight": (dim, 4 * dim),
                f"{block}encoder.linear2.bias": (dim,),
            }
        )
    return shapes


def published_boq(state: dict, feature_map: torch.Tensor, dim=384, blocks=2) -> torch.Tensor:
    """BoQ's forward as published: 3 x 3 projection, LayerNorm, per block a post-norm encoder layer,
    learned queries with self-attention (residual, LayerNorm) and cross-attention (LayerNorm);
    queries of all blocks projected to rows along the query axis, flattened channel-major, L2."""

    def part(module, prefix):
        module.load_state_dict({k.removeprefix(prefix): v for k, v in state.items() if k.startswith(prefix)})
        return module.eval()

    heads = dim // 64
    x = F.conv2d(feature_map, state["aggregator.proj_c.weight"], state["aggregator.proj_c.bias"], padding=1)
    x = F.layer_norm(
        x.flatten(2).transpose(1, 2), (dim,), state["aggregator.norm_input.weight"], state["aggregator.norm_input.bias"]
    )
    outputs = []
    for i in range(blocks):
        block = f"aggregator.boqs.{i}."
        encoder = part(
            nn.TransformerEncoderLayer(dim, heads, 4 * dim, dropout=0.0, batch_first=True), f"{block}encoder."
        )
        x = encoder(x)
        q = state[f"{block}queries"].repeat(len(x), 1, 1)
        q = q + part(nn.MultiheadAttention(dim, heads, batch_first=True), f"{block}self_attn.")(q, q, q)[0]
        q = F.layer_norm(q, (dim,), state[f"{block}norm_q.weight"], state[f"{block}norm_q.bias"])
        out = part(nn.MultiheadAttention(dim, heads, batch_first=True), f"{block}cross_attn.")(q, x, x)[0]
        outputs.append(F.layer_norm(out, (dim,), state[f"{block}norm_out.weight"], state[f"{block}norm_out.bias"]))
    rows = F.linear(
        torch.cat(outputs, dim=1).permute(0, 2, 1), state["aggregator.fc.weight"], state["aggregator.fc.bias"]
    )
    return F.normalize(rows.flatten(1), dim=-1)


def test_boq_reads_its_published_file_and_gives_the_published_descriptor(dinov2_base, tmp_path):
    state = {f"backbone.dino.{k}": v for k, v in dinov2_base.items()}
    state.update(random_tensors(boq_shapes(), seed=4))
    torch.save(state, tmp_path / "dinov2_12288.pth")
    model = load_model("dinov2_boq", tmp_path / "dinov2_12288.pth")
    assert model.network.output_dim == 12288
    with torch.no_grad():
        ours = model.network.eval()(IMAGES)
        feature_map, _ = published_trunk(state, "backbone.dino.", final_norm=False)(IMAGES)  # BoQ: before the norm
        expected = published_boq(state, feature_map)
    torch.testing.assert_close(ours, expected, atol=2e-5, rtol=1e-4)


def test_a_file_of_another_layout_or_with_keys_missing_is_refused_naming_it(dinov2_base, tmp_path):
    state = {f"backbone.model.{k}": v for k, v in dinov2_base.items()}
    state.update(random_tensors(salad_shapes("aggregator.", 64, 128, 256), seed=1))
    torch.save({**state, "aggregator.extra.weight": torch.zeros(2)}, tmp_path / "extra.ckpt")
    with pytest.raises(InstantiationException) as error:
        load_model("dinov2_salad", tmp_path / "extra.ckpt")
    assert (
        "extra.ckpt: not a SALAD weight file: 1 keys this layout has no place for, e.g. ['aggregator.extra.weight']"
        in str(error.value)
    )
    torch.save({k: v for k, v in state.items() if k != "aggregator.dust_bin"}, tmp_path / "short.ckpt")
    with pytest.raises(
        InstantiationException, match=r"short.ckpt: holds no values for 1 parameters, e.g. \['pooling.dustbin'\]"
    ):
        load_model("dinov2_salad", tmp_path / "short.ckpt")
    torch.save(state, tmp_path / "salad_as_boq.pth")
    with pytest.raises(InstantiationException, match="not a BoQ weight file"):
        load_model("dinov2_boq", tmp_path / "salad_as_boq.pth")
    with pytest.raises(InstantiationException, match=r"expected: dino_salad.ckpt .*serizba/salad/releases"):
        load_model("dinov2_salad", tmp_path / "absent.ckpt")


def test_dinovs_own_backbone_file_fills_the_trunk_and_a_new_head_is_random(dinov2_base, tmp_path):
    torch.save(dinov2_base, tmp_path / "dinov2_vitb14_pretrain.pth")
    model = load_model("dinov2", tmp_path / "dinov2_vitb14_pretrain.pth", "model.random_init=true", "model/pooling=boq")
    trunk = dict(model.network.backbone.timm.state_dict())
    assert all(torch.equal(trunk[k], v) for k, v in dinov2_base.items() if k != "mask_token")
    assert model.weights.random_parameters and all(
        name.startswith("pooling.") for name in model.weights.random_parameters
    )
