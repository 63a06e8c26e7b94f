"""List the models known by name, compare a retrained model with a shipped model's card, or (maintainers)
regenerate a shipped model's weights from a training workdir.

    bridge-zoo                                      # names, kinds, where each one is (or how to get it)
    bridge-zoo show long                            # a shipped model's card: recipe, steps, time, numbers
    bridge-zoo compare long work/rebuilt            # work/rebuilt on long's real-image checks, beside its card
    bridge-zoo build demo --from work/demo/train    # after the demo config changed and `make demo`
    bridge-zoo build long --from work/rebuilt --card work/card.json   # a recipe workdir (bridge-train --config=long)

`build` writes bridge_jax/zoo/<name>.npz (float32 params, compressed) and <name>.json (model, working size, the
run's config, steps, training time and machine, last validation, SHA-256, and the entries of --card); the test
suite checks each shipped model against its current config and that it beats zero motion on the synthetic
validation cycles.

`compare NAME WORKDIR` scores WORKDIR (a training workdir, step dir or params dir; anything `--checkpoint`
takes) on the real-image checks whose numbers NAME's card holds (`bridge_jax.eval.real_checks`: Middlebury
Motorcycle disparity, held-out photos under homographies, held-out synthetic frames), at the card's test-time
settings (working size, --refine, --symmetry, --polish and the polish's parameters), and prints one row per check
and metric: the card's number, WORKDIR's, the difference and whether WORKDIR is at least as good (lower is
better; differences under 0.1 % are ties). `--polish both` (the default) also scores WORKDIR without the polish,
beside the card's polish-none numbers where the card has them ("–" where not). `compare long long` took about 7
min on a 2-core AMD EPYC (about 4.5 with `--polish card`); `--limit N` scores only the first N inputs of each
check (a quick look, not the card's numbers); `--json OUT` writes every number.
"""
from __future__ import annotations

import json
import os
import sys

from bridge_jax import cli, files, zoo
from bridge_jax.eval import real_checks


def build_parser():
    p = cli.make_parser("bridge_jax.zoo", __doc__)
    sub = p.add_subparsers(dest="command", metavar="{list,show,compare,build}")
    sub.add_parser("list", help="list the model names (the default)")
    b = sub.add_parser("build", help="write a shipped model's npz + json from a finished training workdir")
    b.add_argument("name", help="registry name of a shipped model (e.g. demo)")
    b.add_argument("--from", dest="workdir", required=True, help="finished training workdir to take the params of")
    b.add_argument("--card", default=None,
                   help="a JSON file whose entries join the model's card, e.g. {\"real_images\": {...}}, the "
                        "numbers of its real-image checks")
    b.add_argument("--machine", default=None, help="the machine it was trained on (default: this one)")
    b.add_argument("--earlier-stage", dest="earlier_stages", action="append", default=[], metavar="CONFIG=WORKDIR",
                   help="a run this one was initialised from, with the --config it ran (repeat, oldest first), "
                        "e.g. long:legacy=work/long_stage1: its steps, lr and training time join the card (a recipe "
                        "workdir lists its stages itself)")
    b.add_argument("--after-shipped", dest="after_shipped", default=None, metavar="CONFIG=NAME",
                   help="this run (or its earliest --earlier-stage) continued the shipped model NAME, trained with "
                        "--config CONFIG: NAME's stages, from its card, come first, e.g. "
                        "long:finetune=long")
    s = sub.add_parser("show", help="print a shipped model's card (recipe, steps, training time, numbers)")
    s.add_argument("name", help="registry name of a shipped model (e.g. long)")
    c = sub.add_parser("compare", help="score a checkpoint on a shipped model's real-image checks, beside its card")
    c.add_argument("name", metavar="NAME", help="registry name of a shipped model whose card to compare with "
                                                "(e.g. long)")
    c.add_argument("workdir", metavar="WORKDIR", help="the checkpoint to score: a training workdir, step dir or "
                                                      "params dir")
    c.add_argument("--polish", default="both", choices=real_checks.POLISH_CHOICES,
                   help="score WORKDIR with the card's test-time polish ('card'), without one ('none'), or with "
                        "both, the polish-none numbers in further columns ('both', the default)")
    c.add_argument("--json", dest="json_out", default=None, metavar="OUT",
                   help="also write the table's rows and every number to this JSON file")
    c.add_argument("--limit", type=int, default=None, metavar="N",
                   help="score only the first N inputs of each check (a quick look: not the card's numbers)")
    cli.add_debug_flag(p)
    return p


@cli.entry_point
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "build":
            if zoo.entry(args.name).kind != "shipped":
                raise ValueError(f"{args.name!r} is not a shipped model (only those are built from a workdir)")
            card = None
            if args.card:
                try:
                    with open(args.card) as f:
                        card = json.load(f)
                except ValueError as e:
                    raise ValueError(f"--card {args.card}: not JSON ({e})") from None
                if not isinstance(card, dict):
                    raise ValueError(f"--card {args.card}: expected a JSON object")
            stages = []
            for spec in args.earlier_stages:
                config, sep, stage_dir = spec.rpartition("=")
                if not sep or not config or not stage_dir:
                    raise ValueError(f"--earlier-stage {spec!r}: expected CONFIG=WORKDIR, "
                                     "e.g. long:legacy=work/long_stage1")
                stages.append((config, stage_dir))
            after = None
            if args.after_shipped:
                config, sep, shipped = args.after_shipped.rpartition("=")
                if not sep or not config or not shipped:
                    raise ValueError(f"--after-shipped {args.after_shipped!r}: expected CONFIG=NAME, "
                                     "e.g. long:finetune=long")
                if shipped not in zoo.names() or zoo.entry(shipped).kind != "shipped":
                    raise ValueError(f"--after-shipped {args.after_shipped!r}: {shipped!r} is not a shipped model "
                                     f"(shipped: {', '.join(n for n in zoo.names() if zoo.entry(n).kind == 'shipped')})")
                after = (config, shipped)
            npz = zoo.build_shipped(args.name, args.workdir, card=card, machine=args.machine, earlier_stages=stages,
                                    after_shipped=after)
            print(f"wrote {npz}")
            return 0
        if args.command == "compare":
            if args.json_out and os.path.isdir(args.json_out):  # said now, not after minutes of scoring
                raise ValueError(f"--json {args.json_out}: is a folder; expected a file name")
            result = real_checks.compare_with_card(args.name, args.workdir, polish=args.polish, limit=args.limit,
                                                   log=lambda line: print(line, file=sys.stderr, flush=True))
            print("\n".join(real_checks.comparison_lines(result)))
            if args.json_out:
                files.write_json(args.json_out, result)
            return 0
        if args.command == "show":
            if zoo.entry(args.name).kind != "shipped":
                raise ValueError(f"{args.name!r} is not a shipped model; `bridge-zoo` lists where it is")
            print("\n".join(zoo.card_lines(args.name)))
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
