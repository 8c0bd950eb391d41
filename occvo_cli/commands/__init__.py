"""Offline subcommands of `occvo`, one module each with add_parser(subparsers) and run(args) -> int."""

COMMANDS = ["run", "eval", "ablation", "eval_map", "train_occ", "eval_occ", "make_occupancy"]
