"""``uevavd train-sam-small`` and ``uevavd finetune-sam``."""

from __future__ import annotations

import argparse
import json
import sys


def _common(p: argparse.ArgumentParser, *, steps: int, lr: float, points: int) -> None:
    p.add_argument("data", metavar="DATA", help="dataset root with ground-truth segmentation (a synthetic world)")
    p.add_argument("--steps", type=int, default=steps, help=f"optimizer steps (default {steps})")
    p.add_argument("--batch-size", type=int, default=8, help="views per step (default 8)")
    p.add_argument("--lr", type=float, default=lr, help=f"AdamW peak learning rate (default {lr})")
    p.add_argument("--points-per-view", type=int, default=points,
                   help=f"ring-point prompts per view per step (default {points})")
    p.add_argument("--per-context", type=int, default=300, help="training views drawn per train context (default 300)")
    p.add_argument("--heldout-per-context", type=int, default=60,
                   help="held-out views per test context (default 60)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1,
                   help="torch CPU threads (default 1: on a shared machine more threads can be much slower)")
    p.add_argument("--fresh", action="store_true", help="ignore an interrupted run's snapshot and start over")


def _check_data(a) -> None:
    """The dataset root and the counts, refused before torch is imported (about 3 s)."""
    from ....config_rules import check_count
    from ....data.reader import read_dataset

    check_count("--threads", a.threads)
    read_dataset(a.data)


def _args(a):
    from .loop import TrainArgs

    return TrainArgs(steps=a.steps, batch_size=a.batch_size, lr=a.lr, points_per_view=a.points_per_view, seed=a.seed)


def _print_report(report: dict, out) -> None:
    print(json.dumps({k: v for k, v in report.items() if k != "train"}, indent=2, sort_keys=True))
    print(f"wrote {out} and {out}.report.json", file=sys.stderr)


def add_train_small(p: argparse.ArgumentParser):
    _common(p, steps=600, lr=1e-3, points=4)
    p.add_argument("--out", default=None,
                   help="checkpoint to write (default $UEVAVD_CACHE/sam/sam_small.safetensors, where the sam "
                        "segmenter looks when no checkpoint is given)")
    p.add_argument("--img-size", type=int, default=64, help="encoder input side in pixels (default 64)")
    p.add_argument("--patch-size", type=int, default=8)
    p.add_argument("--embed-dim", type=int, default=96)
    p.add_argument("--depth", type=int, default=4)
    p.add_argument("--heads", type=int, default=3)

    def run(a) -> int:
        _check_data(a)
        import torch

        from ...sam.model import SmallConfig, default_small_path
        from .data import split_heldout
        from .train_small import train_small

        torch.set_num_threads(a.threads)
        train, held = split_heldout(a.data, per_context=a.per_context, heldout_per_context=a.heldout_per_context,
                                    seed=a.seed)
        cfg = SmallConfig(img_size=a.img_size, patch_size=a.patch_size, embed_dim=a.embed_dim, depth=a.depth,
                          num_heads=a.heads)
        out = a.out or default_small_path()
        report = train_small(train, held, out=out, config=cfg, args=_args(a), fresh=a.fresh)
        _print_report(report, out)
        return 0

    return run


def add_finetune(p: argparse.ArgumentParser):
    _common(p, steps=500, lr=1e-4, points=0)
    p.add_argument("--checkpoint", required=True, help="base SAM checkpoint (.pth or our .safetensors)")
    p.add_argument("--out", required=True, help="where to write the fine-tuned decoder (.safetensors)")
    p.add_argument("--model-type", default="auto", help="vit_b / vit_l / vit_h / vit_t / small / auto (default)")
    p.add_argument("--device", default="auto", help="auto (CUDA when available) / cpu / cuda")

    def run(a) -> int:
        _check_data(a)
        from ....config_rules import check_file

        check_file("--checkpoint", a.checkpoint, "a SAM checkpoint (.pth) or a uevavd .safetensors one (uevavd "
                                                 "train-sam-small writes one)")
        import torch

        from .data import split_heldout
        from .finetune import finetune_model

        torch.set_num_threads(a.threads)
        train, held = split_heldout(a.data, per_context=a.per_context, heldout_per_context=a.heldout_per_context,
                                    seed=a.seed)
        report, _ = finetune_model(a.checkpoint, train, held, out=a.out, model_type=a.model_type,
                                   device=a.device, args=_args(a), fresh=a.fresh)
        _print_report(report, a.out)
        return 0

    return run
