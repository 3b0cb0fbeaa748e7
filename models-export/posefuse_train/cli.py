"""`posefuse-train <command> ...`: one entry point for the trainer's commands."""

from __future__ import annotations

import sys

COMMANDS = {
    "export": "posefuse_train.export",
    "ablation": "posefuse_train.ablation",
    "backbones": "posefuse_train.backbones",
    "report": "posefuse_train.report",
}


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] not in COMMANDS:
        print("usage: posefuse-train {" + ",".join(COMMANDS) + "} [options]  (--help after a command)")
        return 2
    import importlib

    return importlib.import_module(COMMANDS[argv[0]]).main(argv[1:])


if __name__ == "__main__":
    sys.exit(main())
