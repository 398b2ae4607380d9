"""`labrunner sim serve`: the simulated chamber, rate table and IMU as standalone servers on loopback."""

from __future__ import annotations

import argparse
import ipaddress
import json
import signal
import socket
import sys
import threading
import time
from pathlib import Path

from labrunner.commands.types import port, seconds
from labrunner.output_paths import check_output


def register(sub: argparse._SubParsersAction) -> None:
    rehearsal = """\
examples:
  labrunner sim serve --speed 600 --lab-config lab.yaml &   # prints the ports, writes a matching lab.yaml
  labrunner run quick --lab lab.yaml --db rehearsal.db      # the sequencer against it, 600x wall time"""
    sim = sub.add_parser(
        "sim", help="simulated instruments",
        description="The simulated lab on its own: `labrunner sim serve` starts the chamber, rate table and IMU "
                    "as servers speaking the real protocols, to rehearse a lab configuration from another "
                    "process. (A dry run, `labrunner run --sim`, starts its own.)",
        epilog=rehearsal)
    sim_sub = sim.add_subparsers(dest="sim_command", metavar="SIM_COMMAND")
    serve = sim_sub.add_parser(
        "serve", help="serve the simulated chamber, rate table and IMU on loopback",
        description="Start the three simulated instruments as servers (Modbus TCP/RTU chamber, serial-over-TCP "
                    "or pty rate table and IMU) so a lab configuration can be rehearsed from another process. "
                    "Prints the ports and a `ready` JSON line; runs until Ctrl-C, SIGTERM or --duration.",
        epilog=rehearsal)
    serve.add_argument("--speed", type=_speed, default=1.0, metavar="N",
                       help="simulated time runs N times faster than wall time")
    serve.add_argument("--host", default="127.0.0.1", metavar="HOST",
                       help="address to listen on (beyond loopback the simulated lab is reachable from the network: "
                            "a warning says so)")
    serve.add_argument("--chamber-port", type=port, default=0, metavar="PORT", help="Modbus port (0: any free port)")
    serve.add_argument("--table-port", type=port, default=0, metavar="PORT",
                       help="rate table's TCP port with --link tcp (0: any free port)")
    serve.add_argument("--imu-port", type=port, default=0, metavar="PORT",
                       help="IMU's TCP port with --link tcp (0: any free port)")
    serve.add_argument("--chamber-transport", choices=("tcp", "rtu"), default="tcp",
                       help="Modbus TCP, or RTU framing over a TCP socket (socket://)")
    serve.add_argument("--profile", default="watlow_f4", metavar="NAME",
                       help="chamber register-map profile (watlow_f4, watlow_f4t)")
    serve.add_argument("--link", choices=("tcp", "pty"), default="tcp",
                       help="serial lines as socket:// ports or as pseudo-terminals")
    serve.add_argument("--config", type=Path, metavar="SIM.yaml",
                       help="sim configuration: seed, plant parameters, IMU model, faults")
    serve.add_argument("--lab-config", type=Path, metavar="LAB.yaml",
                       help="also write a lab configuration pointing at these sims")
    serve.add_argument("--force", action="store_true", help="overwrite an existing --lab-config file")
    serve.add_argument("--duration", type=seconds, default=None, metavar="S",
                       help="stop after S wall seconds (default: run until Ctrl-C or SIGTERM)")
    serve.set_defaults(func=serve_command)
    sim.set_defaults(func=lambda args: (sim.print_help(), 2)[1])


def _speed(text: str) -> float:
    """--speed: the lab configuration's clock.speed range (a tiny or infinite speed would hang the sims)."""
    from labrunner.lab import RANGES
    from labrunner.yaml_config import Range

    allowed: Range = RANGES["clock.speed"]
    try:
        value: object = float(text)
    except ValueError:
        value = text
    problem = allowed.problem(value)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return float(text)


def is_loopback(host: str) -> bool:
    """Whether `host` is reachable only from this machine (127.0.0.0/8, ::1, a name resolving only to them);
    0.0.0.0 and :: are every interface."""
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        pass
    try:
        addresses = {info[4][0] for info in socket.getaddrinfo(host, None)}
    except (OSError, UnicodeError):
        return False  # the bind will say what is wrong with it
    return bool(addresses) and all(ipaddress.ip_address(str(a).split("%")[0]).is_loopback for a in addresses)


def serve_command(args: argparse.Namespace) -> int:
    import yaml

    from labrunner import api  # here, not at the top: building the parser must not load the sims

    if args.lab_config:  # before the servers start: a refusal leaves nothing running
        check_output(args.lab_config, inputs=[args.config], force=args.force, option="--lab-config")
    lab = api.serve_sim(config=args.config, speed=args.speed, host=args.host, link=args.link,
                        chamber_transport=args.chamber_transport, profile=args.profile,
                        ports=(args.chamber_port, args.table_port, args.imu_port))
    if not is_loopback(args.host):  # once it listens: a host it cannot bind gets the bind's error alone
        print(f"labrunner sim serve: warning: listening on {args.host}, not loopback: the simulated lab is reachable "
              "from the network (anyone there can drive the simulated chamber, table and IMU)", file=sys.stderr,
              flush=True)
    lab_config = lab.lab_config()
    lab_config["clock"] = {"speed": args.speed}
    if args.lab_config:
        args.lab_config.write_text(yaml.safe_dump(lab_config, sort_keys=False))
    info = {
        "chamber": lab.chamber.url if args.chamber_transport == "rtu" else f"modbus-tcp://{args.host}:{lab.chamber.port}",
        "chamber_profile": args.profile,
        "table": lab.table_port.url,
        "imu": lab.imu_port.url,
        "speed": args.speed,
    }
    print("labrunner sim serve: simulated lab running (Ctrl-C to stop)")
    for key, value in info.items():
        print(f"  {key:16s} {value}")
    print("  ready " + json.dumps(info), flush=True)

    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    t_end = None if args.duration is None else time.monotonic() + args.duration
    try:
        while not stop.is_set():
            if t_end is not None and time.monotonic() >= t_end:
                break
            stop.wait(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        lab.close()
    print("labrunner sim serve: stopped", file=sys.stderr)
    return 0
