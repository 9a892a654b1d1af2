"""The ``uevavd`` command line. Subcommands live beside the code they run and are
imported only when invoked, so ``uevavd --help`` stays fast."""

from __future__ import annotations

import argparse
import errno
import importlib
import os
import signal
import sys
import threading

from .runtime import exit_status, skip_teardown

#: name -> ("module:function" that adds its arguments and returns the handler, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("uevavd.experiments.cli:add_demo", "the quick preset end to end on the synthetic world"),
    "ablate": ("uevavd.experiments.cli:add_ablate", "compare methods over seeds and reward sweeps; writes results and a report"),
    "report": ("uevavd.experiments.cli:add_report", "(re)write DIR/report/report.md, figures and claims from an ablation's files"),
    "synth": ("uevavd.data.synthetic.cli:add_synth", "generate the synthetic UEVAVD world (resumable)"),
    "validate": ("uevavd.data.validate:add_validate", "check a dataset root: names, annotations, views, images; exit 1 on problems"),
    "train-classifier": ("uevavd.perception.cli:add_train_classifier", "train the recognizer (the paper's ResNet18, or a preset's recipe) on train_605"),
    "prepare": ("uevavd.perception.cli:add_prepare", "build the observation table of a dataset for a method"),
    "train": ("uevavd.policy.cli:add_train", "train a method (map, memo_map, ibe_map or a plugin's) on an observation table"),
    "evaluate": ("uevavd.policy.cli:add_evaluate", "evaluate a run, or a model zoo policy (--pretrained), beside the baselines"),
    "train-sam-small": ("uevavd.perception.training.sam.cli:add_train_small", "train the small SAM from scratch on a world's ground truth"),
    "finetune-sam": ("uevavd.perception.training.sam.cli:add_finetune", "fine-tune a SAM checkpoint's mask decoder on ground-truth target masks"),
    "zoo": ("uevavd.experiments.cli:add_zoo", "the model zoo: list, check or rebuild the shipped recognizer and policies"),
    "export-minari": ("uevavd.policy.cli:add_export_minari",
                      "a policy's episodes on a table's split as a portable Minari dataset (offline RL, imitation)"),
    "info": ("uevavd.info:add_info", "version, torch and device, components, config and cache paths"),
    "plugins": ("uevavd.plugins.cli:add_plugins", "list plugins and what each registered, by kind"),
}


def bad_input_types() -> tuple[type[BaseException], ...]:
    """Exceptions that mean bad input rather than a bug: every ``ValueError`` subclass the
    library raises for a value it refuses (ConfigError, WeightsError, TableError,
    DatasetError, AblationError, ...), a missing file, an unknown component name."""
    from .plugins.registry import StrictPluginError, UnknownComponentError

    return (ValueError, FileNotFoundError, UnknownComponentError, StrictPluginError)


_FILE_FOR_FOLDER = "a file stands where a folder is expected: choose another path, or move the file"
_FULL = "free space on that disk, or write elsewhere (--out, UEVAVD_CACHE)"
_FORBIDDEN = "choose a path you may write to, or change its permissions"
#: What to do about each OS fault, said after it on its one line.
OS_FAULT_ADVICE = {
    errno.ENOSPC: _FULL, errno.EDQUOT: _FULL, errno.EACCES: _FORBIDDEN, errno.EPERM: _FORBIDDEN,
    errno.EROFS: "the file system is read-only: choose a writable path",
    errno.EISDIR: "a folder stands where a file is expected: pass a file's path",
    errno.ENOTDIR: _FILE_FOR_FOLDER, errno.EEXIST: _FILE_FOR_FOLDER,  # mkdir over a file (nothing creates exclusively)
    errno.ECHILD: "a worker process died (out of memory?): run the command again; finished work is kept",
    errno.ENAMETOOLONG: "a name in that path is longer than the file system allows: choose a shorter path",
    errno.EFBIG: "a file would pass the file-size limit (ulimit -f, or the file system's): raise it, or write elsewhere",
}
#: OS faults that are the machine's state, not a bug: a full disk, a read-only or forbidden
#: folder, a path that is a file where a folder is needed (and the reverse), a worker process
#: that was killed (ECHILD), a name too long or a file too large for the file system: the faults
#: there is advice for.
OS_FAULTS = frozenset(OS_FAULT_ADVICE)


def os_fault(exc: BaseException) -> bool:
    """True for an :data:`OS_FAULTS` ``OSError``: reported in one line like bad input."""
    return isinstance(exc, OSError) and exc.errno in OS_FAULTS


def error(command: str, exc: BaseException | str) -> int:
    """Bad input (an exception, or a problem already in words) as one line on stderr, exit
    status 2; ``UEVAVD_DEBUG=1`` re-raises. Every command reports through this one helper."""
    if os.environ.get("UEVAVD_DEBUG"):
        raise exc if isinstance(exc, BaseException) else ValueError(exc)
    text = " ".join(str(exc).split())  # one line, whatever the message's own line breaks
    if os_fault(exc) and OS_FAULT_ADVICE[exc.errno] not in text:
        text += f"; {OS_FAULT_ADVICE[exc.errno]}"
    hint = f" ({type(exc).__name__}; UEVAVD_DEBUG=1 shows the traceback)" if isinstance(exc, BaseException) else ""
    print(f"uevavd {command}: error: {text}{hint}", file=sys.stderr)
    return 2


def build_parser() -> argparse.ArgumentParser:
    from .version import __version__

    parser = argparse.ArgumentParser(
        prog="uevavd",
        description="UAV active object detection on UEVAVD: data, perception, RL viewing policies, ablations.",
    )
    parser.add_argument("--version", action="version", version=f"uevavd {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (target, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(_target=target)
    return parser


class Terminated(KeyboardInterrupt):
    """A ``SIGTERM`` (a plain ``kill``, a scheduler's stop): the command stops as on Ctrl-C."""


def _on_sigterm(signum: int, frame: object) -> None:
    raise Terminated


def stopped(exc: KeyboardInterrupt) -> tuple[str, int]:
    """How a command was stopped and its exit status: ("terminated", 143) for SIGTERM,
    ("interrupted", 130) for Ctrl-C."""
    if isinstance(exc, Terminated):
        return "terminated", 128 + signal.SIGTERM
    return "interrupted", 128 + signal.SIGINT


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    # Only the chosen subcommand's module is imported: parse once to find it, then let it
    # add its own arguments and parse again.
    if argv and argv[0] in COMMANDS:
        from .runtime import tune_malloc

        tune_malloc()  # uevavd's own process: reuse freed memory (see uevavd/runtime.py)
        name = argv[0]
        module, func = COMMANDS[name][0].split(":")
        sub = argparse.ArgumentParser(prog=f"uevavd {name}", description=COMMANDS[name][1])
        # SIGTERM stops every stage as Ctrl-C does (its clean-up runs; a worker pool stops its
        # jobs), in the main thread only and only where nothing else handles it
        term = threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGTERM) == signal.SIG_DFL
        if term:
            signal.signal(signal.SIGTERM, _on_sigterm)
        try:  # building the parser may load plugins (a command's choices): a strict failure is one line too
            handler = getattr(importlib.import_module(module), func)(sub)
            args = sub.parse_args(argv[1:])
            return int(handler(args) or 0)
        except KeyboardInterrupt as exc:
            how, code = stopped(exc)
            print(f"{how}; finished work is kept and a rerun resumes", file=sys.stderr)
            return code
        except BrokenPipeError:  # the reader left (`uevavd info | head`): stop quietly, as cat does
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
            return 141
        except Exception as exc:  # noqa: BLE001 - bad input is one line; anything else propagates
            if isinstance(exc, bad_input_types()) or os_fault(exc):
                return error(name, exc)
            raise
        finally:
            if term:
                signal.signal(signal.SIGTERM, signal.SIG_DFL)
    args = parser.parse_args(argv)
    parser.print_help()
    return 0 if args.command is None and not argv else 2


def entry() -> None:
    """The ``uevavd`` console script: :func:`main`, then an exit without the interpreter's teardown."""
    skip_teardown()
    try:
        code = main()
    except SystemExit as exc:  # argparse's refusals and --help
        code = exc.code
    exit_status(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    entry()
