"""How a gaps binary reads its flags, for the deployment checks: the program's name, and its flags as
Abseil sees them, those named by --tryfromenv taken from FLAGS_<name> variables when these are set."""
import pathlib


def program(argv):
    return pathlib.PurePosixPath(argv[0]).name if argv else ""


def effective_flags(argv, environment):
    """{flag name: value} for `--name=value` arguments (dashes read as underscores, as the binaries accept)."""
    flags = {}
    from_env = []
    for arg in argv[1:]:
        if not arg.startswith("--") or "=" not in arg:
            continue
        name, value = arg[2:].split("=", 1)
        name = name.replace("-", "_")
        if name in ("tryfromenv", "fromenv"):
            from_env += value.split(",")
        else:
            flags[name] = value
    for name in from_env:
        if environment.get(f"FLAGS_{name}") is not None:
            flags[name] = str(environment[f"FLAGS_{name}"])
    return flags


def uses_cuda(flags):
    return flags.get("device", "cpu").startswith("cuda")


def listen_port(flags, default):
    return int(flags.get("listen", f":{default}").rpartition(":")[2])
