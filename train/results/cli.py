"""`ddyn results check [--fast] [NAME ...]` and `ddyn results table [--write]`: the committed result files
(results/*.json) re-run and compared, and the README's results table made from them."""
from __future__ import annotations

import sys

from ddyn.errors import DdynError
from ddyn.results.files import RESULTS_DIR, by_name, load_all


def _run_check(args) -> int:
    from ddyn.results.check import check_result

    results = load_all(args.dir)
    chosen = by_name(results, args.names) if args.names else [r for r in results if r.fast or not args.fast]
    if not chosen:
        raise DdynError("no result file to check")
    log = None if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    moved = 0
    for r in chosen:
        for o in check_result(r, keep=args.keep, log=log):
            print(o.line(), flush=True)
            moved += o.status != "PASS"
    print(f"{len(chosen)} result file(s): " + (f"{moved} figure(s) moved or failed" if moved else "every figure holds "
                                                 "its committed value"))
    return 1 if moved else 0


def _run_table(args) -> int:
    from ddyn.results.table import README, readme_with_table, render_table

    results = load_all(args.dir)
    if not args.write:
        print(render_table(results), end="")
        return 0
    text = README.read_text()
    new = readme_with_table(text, results, str(README))
    if new != text:
        README.write_text(new)
        print(f"rewrote the results table in {README}")
    else:
        print(f"{README}: the results table is current")
    return 0


def register(subparsers) -> None:
    """`ddyn results` subcommands (the group's parser)."""
    p = subparsers.add_parser("check", help="re-run the result files' commands and compare each figure with its "
                                            "committed value within the file's tolerance",
                              description="Re-run each named result file (default: every one; --fast: those marked "
                                          "fast) in a temporary folder; one line per figure: PASS or MOVED "
                                          "(old -> new), FAILED if a command fails. Exit 1 if any moved or failed.")
    p.add_argument("names", nargs="*", metavar="NAME", help="result files by name (results/NAME.json)")
    p.add_argument("--fast", action="store_true", help="only the files marked fast (under about 60 s each)")
    p.add_argument("--keep", action="store_true", help="keep the temporary folders (their paths go to stderr)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--dir", default=str(RESULTS_DIR), help="folder of the result files (default: %(default)s)")
    p.set_defaults(func=_run_check)
    t = subparsers.add_parser("table", help="the README's results table made from the result files",
                              description="Print the results table made from results/*.json; --write replaces the "
                                          "table between README.md's two marker comments.")
    t.add_argument("--write", action="store_true", help="rewrite README.md's table")
    t.add_argument("--dir", default=str(RESULTS_DIR), help="folder of the result files (default: %(default)s)")
    t.set_defaults(func=_run_table)
