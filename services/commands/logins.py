"""occvo logins: the client logins of the router `occvo serve` / `occvo up` run (services/logins.py): add one for
another user, host or robot, remove one, list them."""

from __future__ import annotations

import sys

from occvo_services.commands._common import add_json, emit

RESTART_NOTE = "a running `occvo serve` / `occvo up` takes it within a second (it restarts its router)"


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("logins", help="add, remove or list the client logins of the service's router")
    verbs = p.add_subparsers(dest="verb", required=True, help="add, remove or list")
    a = verbs.add_parser("add", help="a new client login with a random password; its streams are NAME.<stream>")
    a.add_argument("name", help="the login: letters, digits, '_' or '-' (the prefix of its stream ids)")
    a.add_argument(
        "--print-config",
        action="store_true",
        help="print its zenoh client config (password included) on stdout for another user or host, instead of "
        "writing it next to the others; there: OCCVO_ZENOH_CONFIG=<file> occvo replay --connect tcp/<host>:7447 ...",
    )
    a.add_argument(
        "--ros2",
        action="store_true",
        help="a robot's: its rmw_zenoh nodes may also publish the ROS 2 node's input topics, subscribe its outputs "
        "and take part in the graph of `occvo serve --ros2` (docs/ros2.md)",
    )
    r = verbs.add_parser("remove", help="remove a client login (its streams' stored data stays)")
    r.add_argument("name", help="the login to remove")
    ls = verbs.add_parser("list", help="the logins and their config files")
    add_json(ls, "the logins")
    for v in (a, r, ls):
        v.set_defaults(func=run)


def run(args) -> int:
    from occvo_services import logins

    folder = logins.logins_dir()
    if args.verb == "add":
        text = logins.add(args.name, folder, write=not args.print_config, ros2=args.ros2)
        if args.print_config:
            sys.stdout.write(text)
        else:
            print(f"login {args.name}: {logins.session_file(args.name, folder)} (OCCVO_ZENOH_CONFIG for its clients)")
        print(f"occvo logins: {RESTART_NOTE}", file=sys.stderr)
    elif args.verb == "remove":
        logins.remove(args.name, folder)
        print(f"login {args.name} removed; {RESTART_NOTE}")
    else:
        users, robots = logins.read_users(folder), set(logins.ros2_logins(folder))
        rows = [
            {
                "login": u,
                "role": "worker" if u in logins.RESERVED else "robot" if u in robots else "client",
                "config": str(logins.session_file(u, folder)) if logins.session_file(u, folder).is_file() else None,
            }
            for u in users
        ]
        if args.json:
            emit(args, {"folder": str(folder), "logins": rows}, "")
        else:
            print(f"{folder}:" if rows else f"no logins in {folder} (`occvo serve` makes them on its first start)")
            for row in rows:
                print(f"  {row['login']:<16} {row['role']:<7} {row['config'] or '(config given out)'}")
    return 0
