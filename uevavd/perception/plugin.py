"""Built-in perception components, registered through the same hooks as any plugin."""

from __future__ import annotations

from ..plugins import hookimpl


@hookimpl
def register_segmenters(registry):
    registry.add("none", "uevavd.perception.segmenters:build_none",
                 summary="No segmentation: no target mask, no surrounding segments")
    registry.add("gt", "uevavd.perception.segmenters:build_gt",
                 summary="Ground-truth instance segmentation from the dataset's seg/ PNGs")
    registry.add("sam", "uevavd.perception.sam:build_sam_segmenter",
                 summary="Segment Anything: target from its box, surroundings from a ring of points")


@hookimpl
def register_encoders(registry):
    registry.add("resnet18", "uevavd.perception.encoders:build_resnet18",
                 summary="torchvision ResNet18 backbone, global-pooled 512-d features")
    registry.add("resnet50", "uevavd.perception.encoders:build_resnet50",
                 summary="torchvision ResNet50 backbone, global-pooled 2048-d features")
    registry.add("efficientnet_lite0", "uevavd.perception.efficientnet:build_efficientnet_lite0",
                 summary="EfficientNet-Lite0 backbone, ImageNet weights from its package (offline), 1280-d features")


@hookimpl
def register_classifiers(registry):
    registry.add("resnet18", "uevavd.perception.classifier:build_resnet18_classifier",
                 summary="ResNet18 recognizer trained on the unoccluded train_605 crops")
    registry.add("efficientnet_lite0", "uevavd.perception.classifier:build_efficientnet_lite0_classifier",
                 summary="EfficientNet-Lite0 recognizer (ImageNet-initialised) trained on the train_605 crops")
