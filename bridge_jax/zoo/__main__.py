"""List the models known by name, or (maintainers) regenerate a shipped model's weights from a training workdir.

    bridge-zoo                                      # names, kinds, where each one is (or how to get it)
    bridge-zoo build demo --from work/demo/train    # after the demo config changed and `make demo`

`build` writes bridge_jax/zoo/<name>.npz (float32 params, compressed) and <name>.json (model, working size, the
run's config, steps, last validation, SHA-256); the test suite checks the shipped model against the current
`demo` config and that it beats zero motion on the synthetic validation cycles.
"""
from __future__ import annotations

import sys

from bridge_jax import cli, zoo


def build_parser():
    p = cli.make_parser("bridge_jax.zoo", __doc__)
    sub = p.add_subparsers(dest="command", metavar="{list,build}")
    sub.add_parser("list", help="list the model names (the default)")
    b = sub.add_parser("build", help="write a shipped model's npz + json from a finished training workdir")
    b.add_argument("name", help="registry name of a shipped model (e.g. demo)")
    b.add_argument("--from", dest="workdir", required=True, help="finished training workdir to take the params of")
    cli.add_debug_flag(p)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "build":
            if zoo.entry(args.name).kind != "shipped":
                raise ValueError(f"{args.name!r} is not a shipped model (only those are built from a workdir)")
            print(f"wrote {zoo.build_shipped(args.name, args.workdir)}")
            return 0
        for name in zoo.names():
            e = zoo.entry(name)
            if e.kind == "shipped":
                kind, where = e.kind, "inside the package"
            elif e.local_path().exists():
                kind, where = e.kind, str(e.local_path())
            else:  # a registry entry whose weights are not on this machine: say how to get them
                kind = "not converted yet"
                where = (f"download from {e.download}, then: {e.how.format(path=e.local_path())}" if e.how
                         else f"{e.local_path()} does not exist")
            print(f"{name:18s} {kind:8s} {where}\n{'':18s} {e.description}")
    except (ValueError, OSError) as e:
        return cli.report_error(e, debug=args.debug)
    return 0


if __name__ == "__main__":
    sys.exit(main())
