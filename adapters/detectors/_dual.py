"""What the dual-stream YOLOv5-family plugins (ICAFusion, EME, CMA-Det) share: their spec, their build (the trunk
size, the network's own options, then the NMS settings and the weights) and their weight loading.

Kept free of torch imports so that registering the plugins stays fast (``harness --help``, ``harness list``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Mapping

from harness.api import DetectorSpec, Reference

if TYPE_CHECKING:
    from adapters.detectors.yolo.v5 import AnchorDetector


def load_weights(model: Any, state_dict: Mapping[str, Any] | Any, name: str) -> dict:
    """Load a YOLOv5-layout state dict (a mapping or a file path) into ``model``; returns the key report
    (``loaded``, ``missing``, ``unexpected``, ``mismatched``)."""
    from adapters.detectors.yolo.v5 import load_state_dict_report, read_weights

    return load_state_dict_report(model, read_weights(state_dict, name), name)


#: The build options every dual-stream detector takes besides its network's own: the weights and the NMS settings.
FINISH_OPTIONS = ("weights", "conf", "iou", "max_det", "multi_label", "max_nms")
#: The trunk size options of every dual-stream build: a YOLOv5 size letter, or explicit width and depth multiples.
TRUNK_OPTIONS = ("scale", "width", "depth")


def build_dual(
    network: type[AnchorDetector],
    num_classes: int,
    in_channels: int,
    options: dict[str, Any],
    net_options: tuple[str, ...] = (),
    known: tuple[str, ...] = (),
) -> Any:
    """A dual-stream build: ``network(num_classes, trunk, **its own options)``, then ``finish_build``; errors name
    the detector by ``network.name``.

    ``options`` (the build's keyword options) hold the ``TRUNK_OPTIONS`` (a ``scale`` letter, each multiple
    overridable by an explicit ``width``/``depth``), the network's ``net_options`` (those not given keep the
    network's defaults) and the ``FINISH_OPTIONS``; anything else must be among ``known`` (also passed on to the
    network), else a ``ConfigError`` naming it."""
    from adapters.detectors.yolo.v5 import Trunk, resolve_scale

    name = network.name
    size = {k: options.pop(k) for k in TRUNK_OPTIONS if k in options}
    own = {k: options.pop(k) for k in net_options if k in options}
    finish = finish_options(name, options, (*TRUNK_OPTIONS, *net_options, *known))
    width, depth = resolve_scale(name, size["scale"], size.get("width"), size.get("depth"))
    model = network(num_classes, Trunk(in_channels, width, depth), **own, **options)
    return finish_build(model, name, **finish)


def finish_options(name: str, options: dict[str, Any], known: tuple[str, ...] = ()) -> dict[str, Any]:
    """Take the ``FINISH_OPTIONS`` out of a build's keyword ``options`` (for ``finish_build``); what is left must be
    among ``known`` (the build's other options), else a ``ConfigError`` naming the unknown ones and every option the
    build takes."""
    from adapters.detectors.yolo.v5 import check_options

    finish = {k: options.pop(k) for k in FINISH_OPTIONS if k in options}
    check_options(name, options, (*known, *FINISH_OPTIONS))
    return finish


def finish_build(model: Any, name: str, weights: Any = None, **nms: Any) -> Any:
    """The end of every dual-stream build: the NMS settings of the config (``nms``, the keywords of
    ``set_inference_options``; ``None`` keeps the model's), then ``weights`` (a YOLOv5-layout state dict or file,
    when given) with the key report kept as ``model.load_report``."""
    from adapters.detectors.yolo.v5 import set_inference_options

    set_inference_options(model, **nms)
    if weights is not None:
        model.load_report = load_weights(model, weights, name)
    return model


def dual_stream_spec(
    name: str,
    build: Callable[..., Any],
    description: str,
    label: str,
    *,
    seed: tuple[float, float],
    nms_iou: float,
    load_official: Callable[..., dict] | None,
) -> DetectorSpec:
    """A dual-stream detector fed ``(rgb, thermal)``, the thermal encoding (ir8 by default, as the baselines' own
    code reads its thermal images) replicated to three channels. ``seed``: the parameters (M) and GFLOPs the seed
    paper publishes for it (8 classes, 640 x 640)."""
    return DetectorSpec(
        name=name,
        build=build,
        input_kind="dual",
        description=description,
        label=label,
        reference=Reference(params_m=seed[0], gflops=seed[1], source="seed paper", num_classes=8),
        default_thermal_encoding="ir8",
        thermal_channels=3,
        defaults={"eval": {"iou": nms_iou}},
        load_official=load_official,
    )
