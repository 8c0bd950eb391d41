"""`occvo` sub-commands of the service side, one module each exposing add_parser(subparsers) and run(args) -> int.

occvo_cli.cli adds occvo_services.commands.<name> for every name in COMMANDS.
"""

COMMANDS = ["serve", "up", "logins", "replay", "poses", "tile", "map_info", "view", "store"]
