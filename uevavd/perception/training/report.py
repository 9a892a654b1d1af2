"""The classifier's report: held-out clean accuracy, and accuracy against the target's
visible fraction on the training contexts (markdown table + PNG)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ...atomic import atomic_save, atomic_write
from ...data.splits import TARGETS

BINS = np.linspace(0.0, 1.0, 11)


def accuracy_by_visibility(correct: np.ndarray, visible: np.ndarray, bins: np.ndarray = BINS):
    """Per bin of visible fraction: ``(lo, hi, n, accuracy)`` rows (NaN accuracy if empty).
    The last bin includes 1.0; a fully occluded view (visible 0) falls in the first."""
    idx = np.clip(np.digitize(visible, bins[1:-1], right=False), 0, len(bins) - 2)
    rows = []
    for b in range(len(bins) - 1):
        sel = idx == b
        rows.append((float(bins[b]), float(bins[b + 1]), int(sel.sum()),
                     float(correct[sel].mean()) if sel.any() else float("nan")))
    return rows


def visibility_report(model, manifest, weights_path: Path, info: dict, *, decoder, max_views: int = 3000,
                      seed: int = 0) -> tuple[Path, Path | None]:
    """Write ``<weights>.md`` (and ``<weights>.png`` when there are training contexts)."""
    from .classifier import input_norm, predict

    recs = [r for r in manifest.records if r.split == "train" and r.visible is not None]
    rng = np.random.default_rng(seed)
    if len(recs) > max_views:
        recs = [recs[i] for i in np.sort(rng.choice(len(recs), max_views, replace=False))]
    lines = [
        f"# Classifier report: {weights_path.name}",
        "",
        f"- initial weights: {info['init']}; {info['settings']['epochs']} epochs, "
        f"{info['n_train']} training crops, {info['n_val']} held-out crops "
        f"({len(info['val_views'])} held-out viewpoints), {info['seconds']} s",
        f"- **held-out clean accuracy: {info['val_accuracy']:.4f}**",
        "",
        "| epoch | loss | held-out accuracy |",
        "|---|---|---|",
        *[f"| {h['epoch']} | {h['loss']:.4f} | {h['val_accuracy']:.4f} |" for h in info["history"]],
        "",
    ]
    png = None
    if recs:
        images = decoder.images([r.image for r in recs])
        labels = np.array([TARGETS.index(r.target) for r in recs])
        visible = np.array([r.visible for r in recs], np.float64)
        correct = predict(model, images, norm=input_norm(info["settings"].get("arch", "resnet18"))).argmax(1) == labels
        rows = accuracy_by_visibility(correct, visible)
        lines += [
            f"## Accuracy against visible fraction (training contexts, {len(recs)} views)",
            "",
            "| visible fraction | views | accuracy |",
            "|---|---|---|",
            *[f"| {lo:.1f}-{hi:.1f} | {n} | {'-' if n == 0 else f'{acc:.3f}'} |" for lo, hi, n, acc in rows],
            "",
        ]
        png = weights_path.with_suffix(".png")
        _plot(rows, png, info["val_accuracy"])
        lines.append(f"![accuracy vs visible fraction]({png.name})")
    else:
        lines.append("No training contexts with a known visible fraction: no occlusion curve.")
    md = weights_path.with_suffix(".md")
    atomic_write(md, "\n".join(lines) + "\n")
    return md, png


def _plot(rows, path: Path, clean_acc: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mids = [(lo + hi) / 2 for lo, hi, n, _ in rows if n]
    accs = [acc for _, _, n, acc in rows if n]
    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    ax.plot(mids, accs, "o-", label="training contexts")
    ax.axhline(clean_acc, ls="--", c="gray", label=f"held-out clean views ({clean_acc:.3f})")
    ax.set(xlabel="visible fraction of the target", ylabel="accuracy", xlim=(0, 1), ylim=(0, 1.02))
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    try:
        atomic_save(path, fig.savefig)
    finally:
        plt.close(fig)
