"""Plant one-line mutations in the numerical core and check the mapped tests catch them.

Slow and not part of CI. Run from the repository root, e.g.

    python tools/mutate.py --modules invctl/contact/lcp.py --max-mutants 20 --out report.txt

Each mutant rewrites one token on one source line, runs the mapped test files with
``pytest -x -q -p no:cacheprovider`` and restores the file byte-identical afterwards (also
after Ctrl-C). The target files must be committed first, so a crash can never leave a planted
bug unnoticed. The run over the core, two processes each in its own clone (two shards would
see each other's mutants in one tree), then the survivors again after new tests:

    python tools/mutate.py --max-mutants 16 --per-folder --shard 1/2 --out s1.txt   # clone 1
    python tools/mutate.py --max-mutants 16 --per-folder --shard 2/2 --out s2.txt   # clone 2
    python tools/mutate.py --max-mutants 16 --per-folder --rerun s1.txt s2.txt --out all.txt

(with ``--shard`` again on the re-run, ``--merge --rerun all1.txt all2.txt`` joins the halves).
``@FILE`` reads arguments from FILE, one a line (e.g. ``--only`` and a fixed list of keys).
"""
from __future__ import annotations

import argparse
import ast
import io
import os
import random
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import tokenize
from dataclasses import dataclass
from pathlib import Path

# Module -> test files that cover it (files that import it, directly or through the
# function users call). Modules not listed fall back to name heuristics
# (tests/test_*<stem>*.py), then to FALLBACK_TESTS.
_ANALYSIS = ["tests/test_analysis_linear.py", "tests/test_analysis_textbook.py",
             "tests/test_normal_form.py"]
_OCP = ["tests/test_ocp.py", "tests/test_bounds_between_nodes.py"]
_INVERSION = ["tests/test_inversion.py", "tests/test_inversion_plan.py"]
TEST_MAP = {
    "invctl/model/linalg.py": ["tests/test_linear_solves.py", "tests/test_model.py"],
    "invctl/model/multibody.py": ["tests/test_model.py", "tests/test_analysis_textbook.py"],
    "invctl/model/params.py": ["tests/test_model.py", "tests/test_sensitivity.py"],
    "invctl/model/region.py": ["tests/test_region_closed_form.py", "tests/test_region_sampling.py",
                               "tests/test_model.py"],
    "invctl/analysis/auxiliary.py": _ANALYSIS,
    "invctl/analysis/equilibrium.py": ["tests/test_equilibrium_solver.py"] + _ANALYSIS + [
        "tests/test_statespace.py"],
    "invctl/analysis/identify.py": ["tests/test_identify.py"],
    "invctl/analysis/internal.py": ["tests/test_zeros.py"] + _ANALYSIS,
    "invctl/analysis/linearize.py": ["tests/test_identify.py", "tests/test_zeros.py",
                                     "tests/test_statespace.py"],
    "invctl/analysis/relative_degree.py": _ANALYSIS + ["tests/test_numbers_users_see.py"],
    "invctl/analysis/statespace.py": ["tests/test_statespace.py"],
    "invctl/analysis/summary.py": ["tests/test_analysis_manipulator.py"],
    "invctl/analysis/zeros.py": ["tests/test_zeros.py", "tests/test_analysis_linear.py"],
    "invctl/contact/equilibria.py": ["tests/test_mechanisms_000.py", "tests/test_sixbar.py"],
    "invctl/contact/lcp.py": ["tests/test_lcp_tolerances.py", "tests/test_numbers_users_see.py",
                              "tests/test_contact.py", "tests/test_lcp_compiled.py"],
    "invctl/contact/linkage.py": ["tests/test_mechanisms_000.py"],
    "invctl/contact/mechanics.py": ["tests/test_contact.py", "tests/test_chain.py"],
    "invctl/contact/reduction.py": ["tests/test_chain.py"],
    "invctl/contact/structure.py": ["tests/test_mechanisms_000.py", "tests/test_sixbar.py",
                                    "tests/test_chain.py"],
    "invctl/control/funnel.py": ["tests/test_funnel.py"],
    "invctl/control/funnel_design.py": ["tests/test_funnel_design.py"],
    "invctl/control/funnel_nmp.py": ["tests/test_funnel.py", "tests/test_funnel_design.py",
                                     "tests/test_normal_form.py"],
    "invctl/control/juggling.py": ["tests/test_clearance.py", "tests/test_contact.py"],
    "invctl/control/new_output.py": ["tests/test_funnel_design.py"],
    "invctl/control/pdplus.py": ["tests/test_timestepping.py", "tests/test_chain.py"],
    "invctl/control/preload.py": ["tests/test_contact.py", "tests/test_timestepping.py"],
    "invctl/control/switched.py": ["tests/test_switched_sim.py", "tests/test_switched_stability.py"],
    "invctl/inversion/backends.py": ["tests/test_numbers_users_see.py", "tests/test_inversion.py",
                                     "tests/test_ocp.py"],
    "invctl/inversion/banded.py": _INVERSION,
    "invctl/inversion/boundary.py": ["tests/test_bounds_between_nodes.py",
                                     "tests/test_analysis_manipulator.py"],
    "invctl/inversion/bounded.py": _OCP,
    "invctl/inversion/cache.py": _OCP + ["tests/test_owned_objects.py"],
    "invctl/inversion/collocation.py": _INVERSION + _OCP,
    "invctl/inversion/compiled.py": ["tests/test_library.py"] + _INVERSION,
    "invctl/inversion/guess.py": _INVERSION + _OCP,
    "invctl/inversion/internal_bvp.py": ["tests/test_normal_form.py"],
    "invctl/inversion/mintime.py": _OCP,
    "invctl/inversion/normal_form.py": ["tests/test_normal_form.py"],
    "invctl/inversion/ocp.py": _OCP,
    "invctl/inversion/options.py": _INVERSION + _OCP,
    "invctl/inversion/plan.py": ["tests/test_inversion_plan.py"],
    "invctl/inversion/problem.py": _OCP,
    "invctl/inversion/refine.py": ["tests/test_mesh_refinement.py"] + _INVERSION + _OCP,
    "invctl/inversion/schemes.py": _INVERSION + _OCP,
    "invctl/inversion/result.py": ["tests/test_bounds_between_nodes.py", "tests/test_inversion.py"],
    "invctl/inversion/sensitivity.py": ["tests/test_sensitivity.py"],
    "invctl/inversion/solver.py": ["tests/test_inversion_solver.py", "tests/test_inversion.py"],
    "invctl/model/urdf.py": ["tests/test_urdf.py"],
    "invctl/inversion/servo.py": ["tests/test_linear_solves.py"],
    "invctl/inversion/square.py": ["tests/test_inversion_residuals.py"] + _INVERSION + _OCP,
    "invctl/inversion/verify.py": ["tests/test_numbers_users_see.py", "tests/test_inversion.py"],
    "invctl/simulate/closed_loop.py": ["tests/test_closed_loop_advice.py", "tests/test_numbers_users_see.py",
                                       "tests/test_closed_loop.py",
                                       "tests/test_closed_loop_setup.py"],
    "invctl/simulate/codegen.py": ["tests/test_timestepping.py"],
    "invctl/simulate/contact_record.py": ["tests/test_contact.py", "tests/test_results_shape.py"],
    "invctl/simulate/event_driven.py": ["tests/test_timestepping.py", "tests/test_mechanisms_000.py"],
    "invctl/simulate/switched.py": ["tests/test_switched_events.py", "tests/test_switched_sim.py",
                                    "tests/test_switched_cli.py"],
    "invctl/simulate/timestepping.py": ["tests/test_timestepping.py"],
}
FALLBACK_TESTS = ["tests/test_inversion.py", "tests/test_model.py", "tests/test_contact.py"]
CORE = ["invctl/model", "invctl/analysis", "invctl/inversion", "invctl/control",
        "invctl/contact", "invctl/simulate"]

SWAP_NAMES = {"argmax": "argmin", "argmin": "argmax", "max": "min", "min": "max",
              "maximum": "minimum", "minimum": "maximum", "nanmax": "nanmin", "nanmin": "nanmax"}
CMP_SWAPS = {ast.Lt: ["<=", ">"], ast.LtE: ["<", ">="], ast.Gt: [">=", "<"],
             ast.GtE: [">", "<="], ast.Eq: ["!="], ast.NotEq: ["=="]}
MESSAGE_CALLS = {"print", "warn", "debug", "info", "warning", "error", "exception",
                 "write"}


@dataclass
class Mutant:
    path: str     # relative to the root, forward slashes
    line: int     # 1-based
    col: int      # 0-based column of the replaced text
    old: str
    new: str
    nth: int = 1  # which occurrence of the same mutation on this line

    @property
    def key(self):
        more = f" ({self.nth})" if self.nth > 1 else ""
        return f"{self.path}:{self.line}:{self.old} -> {self.new}{more}".rstrip()

    def apply(self, source):
        lines = source.splitlines(keepends=True)
        text = lines[self.line - 1]
        assert text[self.col:self.col + len(self.old)] == self.old, self.key
        lines[self.line - 1] = text[:self.col] + self.new + text[self.col + len(self.old):]
        return "".join(lines)


class _Finder(ast.NodeVisitor):
    """Collect one-token mutations outside docstrings, strings, messages and raise statements."""

    def __init__(self, path, source):
        self.path, self.source = path, source
        self.lines = source.splitlines(keepends=True)
        self.ops = [t for t in tokenize.generate_tokens(io.StringIO(source).readline)
                    if t.type == tokenize.OP or t.string in ("and", "or")]
        self.found = []

    def add(self, line, col, old, new):
        if self.lines[line - 1][col:col + len(old)] == old:
            self.found.append(Mutant(self.path, line, col, old, new))

    def op_between(self, left, right, texts):
        """The operator token in ``texts`` between two nodes on the same line, or None."""
        if left.end_lineno != right.lineno:
            return None
        for tok in self.ops:
            (ln, c), s = tok.start, tok.string
            if ln == left.end_lineno and left.end_col_offset <= c < right.col_offset and s in texts:
                return tok
        return None

    # subtrees that are never mutated
    def visit_Raise(self, node):
        pass

    def visit_JoinedStr(self, node):
        pass

    def visit_Assert(self, node):
        pass

    def visit_Expr(self, node):
        if not (isinstance(node.value, ast.Constant) and isinstance(node.value.value, str)):
            self.generic_visit(node)

    def visit_Call(self, node):
        f = node.func
        name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None
        if name in MESSAGE_CALLS or (name or "").endswith("Error"):
            return
        if name == "abs" and f.lineno == f.end_lineno:
            seg = ast.get_source_segment(self.source, f)
            if seg in ("abs", "np.abs", "numpy.abs", "ca.fabs", "np.fabs"):
                self.add(f.lineno, f.col_offset, seg, "")
        for kw in node.keywords:
            self.bool_const(kw.value)
        self.generic_visit(node)

    def visit_Name(self, node):
        if node.id in SWAP_NAMES and isinstance(node.ctx, ast.Load):
            self.add(node.lineno, node.col_offset, node.id, SWAP_NAMES[node.id])

    def visit_Attribute(self, node):
        if node.attr in SWAP_NAMES and node.end_lineno == node.lineno:
            col = node.end_col_offset - len(node.attr)
            self.add(node.lineno, col, node.attr, SWAP_NAMES[node.attr])
        self.generic_visit(node)

    def visit_Compare(self, node):
        nodes = [node.left] + node.comparators
        for op, a, b in zip(node.ops, nodes, nodes[1:]):
            for new in CMP_SWAPS.get(type(op), []):
                tok = self.op_between(a, b, {"<", "<=", ">", ">=", "==", "!="})
                if tok:
                    self.add(tok.start[0], tok.start[1], tok.string, new)
        self.generic_visit(node)

    def visit_BinOp(self, node):
        if any(isinstance(x, ast.JoinedStr) or (isinstance(x, ast.Constant) and
                                                isinstance(x.value, str))
               for x in (node.left, node.right)):
            return  # string building, not arithmetic
        pairs = {ast.Add: ("+", "-"), ast.Sub: ("-", "+")}
        num = [isinstance(x, ast.Constant) and type(x.value) in (int, float)
               for x in (node.left, node.right)]
        if any(num):
            pairs.update({ast.Mult: ("*", "/"), ast.Div: ("/", "*")})
        if type(node.op) in pairs:
            old, new = pairs[type(node.op)]
            tok = self.op_between(node.left, node.right, {old})
            if tok:
                self.add(tok.start[0], tok.start[1], old, new)
        for x, is_num in zip((node.left, node.right), num):
            if is_num and x.lineno == x.end_lineno:
                seg = ast.get_source_segment(self.source, x)
                self.add(x.lineno, x.col_offset, seg, _bump(x.value))
        self.generic_visit(node)

    def visit_BoolOp(self, node):
        old, new = ("and", "or") if isinstance(node.op, ast.And) else ("or", "and")
        tok = self.op_between(node.values[0], node.values[1], {old})
        if tok:
            self.add(tok.start[0], tok.start[1], old, new)
        self.generic_visit(node)

    def visit_FunctionDef(self, node):
        for d in node.args.defaults + [d for d in node.args.kw_defaults if d is not None]:
            self.bool_const(d)
        self.generic_visit(node)

    visit_AsyncFunctionDef = visit_FunctionDef

    def bool_const(self, node):
        if isinstance(node, ast.Constant) and isinstance(node.value, bool):
            old = str(node.value)
            self.add(node.lineno, node.col_offset, old, str(not node.value))


def _bump(value):
    """A different numeric literal: 0 -> 1, 1 <-> 2, other ints + 1, other floats * 10."""
    if value in (0, 1, 2):
        return repr(type(value)({0: 1, 1: 2, 2: 1}[value]))
    return repr(value + 1) if isinstance(value, int) else repr(float(f"{value * 10:.12g}"))


def find_mutants(root, path):
    source = (root / path).read_text()
    finder = _Finder(path, source)
    finder.visit(ast.parse(source))
    seen, out = set(), []
    for m in sorted(finder.found, key=lambda m: (m.line, m.col, m.new)):
        if (m.line, m.col, m.old, m.new) in seen:
            continue
        seen.add((m.line, m.col, m.old, m.new))
        m.nth = 1 + sum((o.line, o.old, o.new) == (m.line, m.old, m.new) for o in out)
        out.append(m)
    return out


def parses(root, mutant):
    """Does the mutated file still parse? (Every mutation kind keeps the syntax; checked anyway.)"""
    try:
        ast.parse(mutant.apply((root / mutant.path).read_text()))
    except SyntaxError:
        return False
    return True


def tests_for(root, path):
    if path in TEST_MAP:
        return TEST_MAP[path]
    stem = Path(path).stem.lstrip("_")
    guess = sorted(str(p.relative_to(root)) for p in (root / "tests").glob(f"test_*{stem}*.py"))
    return guess or [t for t in FALLBACK_TESTS if (root / t).exists()]


def expand(root, paths):
    out = []
    for p in paths:
        full = root / p
        files = sorted(full.rglob("*.py")) if full.is_dir() else [full]
        out += [f.relative_to(root).as_posix() for f in files]
    return out


def uncommitted(root, paths):
    r = subprocess.run(["git", "status", "--porcelain", "--", *paths], cwd=root,
                       capture_output=True, text=True)
    if r.returncode != 0:
        return r.stderr.strip() or "not a git repository"
    return r.stdout.strip()


def read_equivalent(path):
    """Lines ``file:line:old -> new  # reason``; blank lines and ``#`` comments are skipped."""
    out = {}
    if path:
        for raw in Path(path).read_text().splitlines():
            if raw.strip() and not raw.lstrip().startswith("#"):
                key, _, reason = raw.partition("#")
                out[key.strip()] = reason.strip() or "no reason given"
    return out


def run_tests(root, tests, timeout):
    """'passed', 'failed' or 'timeout' for one pytest run in its own process group."""
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1", MPLBACKEND="Agg",
               PYTHONPATH=os.pathsep.join(filter(None, [str(root), os.environ.get("PYTHONPATH")])))
    proc = subprocess.Popen([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
                             *tests], cwd=root, env=env, start_new_session=True,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        rc = proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        return "timeout"
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        raise
    return "passed" if rc == 0 else "failed"


def run_mutant(root, mutant, tests, timeout, backup_dir):
    target = root / mutant.path
    backup = Path(backup_dir) / mutant.path.replace("/", "__")
    shutil.copy2(target, backup)
    try:
        target.write_text(mutant.apply(backup.read_text()))
        outcome = run_tests(root, tests, timeout)
    finally:
        shutil.copy2(backup, target)
    return {"passed": "survived", "failed": "killed", "timeout": "timeout"}[outcome]


def report(results, equivalent, baseline_failed):
    lines, survivors, equiv = [], [], []
    by_module, by_folder = {}, {}
    zero = {"killed": 0, "survived": 0, "timeout": 0, "equivalent": 0}
    for m, status in results:
        if status == "survived" and m.key in equivalent:
            status = "equivalent"
            equiv.append(f"  {m.key}  # {equivalent[m.key]}")
        elif status == "survived":
            survivors.append(f"  {m.key}")
        by_module.setdefault(m.path, dict(zero))[status] += 1
        by_folder.setdefault(str(Path(m.path).parent.as_posix()) + "/", dict(zero))[status] += 1
    lines.append(f"{'module':45s} killed survived timeout equivalent  kill rate")
    total = dict(zero)
    for path, c in sorted(by_module.items()):
        for k in total:
            total[k] += c[k]
        lines.append(_row(path, c))
    if len(by_folder) > 1:
        lines.append(f"{'folder':45s}")
        lines += [_row(path, c) for path, c in sorted(by_folder.items())]
    lines.append(_row("total", total))
    lines.append("kill rate = (killed + timeout) / (mutants - equivalent)")
    for path in baseline_failed:
        lines.append(f"skipped {path}: its tests fail without any mutation")
    lines.append(f"survivors ({len(survivors)}):")
    lines += survivors or ["  none"]
    lines.append(f"equivalent mutants that survived ({len(equiv)}):")
    lines += equiv or ["  none"]
    return "\n".join(lines)


def _row(name, c):
    counted = c["killed"] + c["survived"] + c["timeout"]
    rate = f"{100 * (c['killed'] + c['timeout']) / counted:5.1f}%" if counted else "    -"
    return (f"{name:45s} {c['killed']:6d} {c['survived']:8d} {c['timeout']:7d} "
            f"{c['equivalent']:10d}  {rate}")


LINE = re.compile(r"^\[\d+/\d+\]\s+(killed|survived|timeout)\s+[\d.]+s\s+(.+?)\s*$")


def read_results(paths):
    """Mutant key -> status from the per-mutant lines of earlier reports (later files win)."""
    out = {}
    for path in paths:
        for raw in Path(path).read_text().splitlines():
            hit = LINE.match(raw)
            if hit:
                out[hit.group(2)] = hit.group(1)
    return out


def sample(mutants, n, seed, per_folder=None):
    """``n`` mutants drawn with ``seed``; with ``per_folder`` (folder -> files), ``n`` from each."""
    rng = random.Random(seed)
    groups = per_folder or {None: None}
    out = []
    for files in groups.values():
        pool = [m for m in mutants if files is None or m.path in files]
        out += pool if len(pool) <= n else rng.sample(pool, n)
    return sorted(out, key=lambda m: (m.path, m.line, m.col, m.new))


def _interrupt(*_):
    raise KeyboardInterrupt


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], fromfile_prefix_chars="@")
    ap.add_argument("--modules", nargs="+", default=CORE, metavar="PATHS",
                    help="files or folders to mutate, relative to --root (default: the core)")
    ap.add_argument("--max-mutants", type=int, default=None, metavar="N",
                    help="sample N mutants (with --per-folder: N from each --modules path)")
    ap.add_argument("--per-folder", action="store_true",
                    help="stratify the --max-mutants sample over the --modules paths")
    ap.add_argument("--only", nargs="+", metavar="KEY", default=None,
                    help="run just these mutants, keys as printed, e.g. 'invctl/x.py:12:< -> <=' "
                         "(--modules, --max-mutants and --per-folder are then ignored)")
    ap.add_argument("--merge", action="store_true",
                    help="with --rerun: carry survivors over as well, run only mutants missing from the "
                         "reports (merges shard reports into one)")
    ap.add_argument("--no-baseline", action="store_true",
                    help="skip the unmutated run of each test set (only when it just passed, e.g. re-runs)")
    ap.add_argument("--report-only", action="store_true",
                    help="with --merge: run nothing; mutants missing from the reports are listed as not run")
    ap.add_argument("--shard", metavar="K/N", default=None,
                    help="run only every N-th mutant of the sample, starting at the K-th (1-based)")
    ap.add_argument("--rerun", nargs="+", metavar="REPORT", default=None,
                    help="re-run the survivors listed in these earlier reports (the same "
                         "--modules, --max-mutants, --per-folder and --seed) and carry their "
                         "killed and timeout results over")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=300.0, metavar="S",
                    help="seconds per mutant's test run; longer counts as killed (timeout)")
    ap.add_argument("--list", action="store_true", help="print the mutants, run nothing")
    ap.add_argument("--out", metavar="FILE", help="write the report here as well")
    ap.add_argument("--equivalent", metavar="FILE",
                    help="known equivalent mutants, lines 'file:line:old -> new  # reason'")
    ap.add_argument("--root", default=".", help="repository root (default: current folder)")
    args = ap.parse_args(argv)

    root = Path(args.root).resolve()
    missing = [p for p in args.modules if not (root / p).exists()]
    if missing:
        ap.error(f"no such file or folder under {root}: {', '.join(missing)}")
    groups = {p: expand(root, [p]) for p in args.modules}
    files = [f for p in args.modules for f in groups[p]]
    mutants = [] if args.only else [m for f in files for m in find_mutants(root, f)]
    if args.max_mutants is not None:
        mutants = sample(mutants, args.max_mutants, args.seed,
                         groups if args.per_folder else None)
    earlier = {}
    if args.only:
        args.only = [k.strip() for k in args.only]
        paths = sorted({k.split(":")[0] for k in args.only if (root / k.split(":")[0]).is_file()})
        known = {m.key: m for f in paths for m in find_mutants(root, f)}
        unknown = [k for k in args.only if k not in known]
        if unknown:
            ap.error("no such mutant (run with --list to see the keys): " + "; ".join(unknown))
        mutants = [known[k] for k in args.only]
    if args.rerun:
        earlier = read_results(args.rerun)
        keys = {m.key for m in mutants}
        unknown = sorted(set(earlier) - keys)
        if unknown:
            ap.error(f"{len(unknown)} mutants of {', '.join(args.rerun)} are not in this sample "
                     f"(source changed, or other --modules/--max-mutants/--seed?), e.g. "
                     f"{unknown[0]}")
    if args.shard:
        k, _, n = args.shard.partition("/")
        if not (k.isdigit() and n.isdigit() and 1 <= int(k) <= int(n)):
            ap.error(f"--shard {args.shard}: expected K/N with 1 <= K <= N, e.g. 1/2")
        mutants = mutants[int(k) - 1::int(n)]
    broken = [m for m in mutants if not parses(root, m)]
    if broken:
        print(f"dropped {len(broken)} mutants that do not parse: " + "; ".join(m.key for m in broken),
              file=sys.stderr)
        mutants = [m for m in mutants if m not in broken]
    if args.list:
        for m in mutants:
            print(f"{m.key}    [{', '.join(tests_for(root, m.path))}]")
        print(f"{len(mutants)} mutants")
        return 0

    dirty = uncommitted(root, sorted({m.path for m in mutants}))
    if dirty:
        print("refusing to mutate files with uncommitted changes (or outside git):\n" + dirty +
              "\nrun `git status`, then commit or stash these changes and start again.",
              file=sys.stderr)
        return 2
    equivalent = read_equivalent(args.equivalent)
    signal.signal(signal.SIGTERM, _interrupt)

    results, baseline, failed_baseline = [], {}, []
    interrupted, carried, not_run = False, 0, []
    log = open(args.out, "w") if args.out else None

    def say(text):
        print(text, flush=True)
        if log:
            log.write(text + "\n")
            log.flush()

    say(f"# python tools/mutate.py {' '.join(shlex.quote(a) for a in (argv or sys.argv[1:]))}")
    say(f"# seed {args.seed}, {len(mutants)} mutants, started "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    with tempfile.TemporaryDirectory(prefix="mutate-") as backup_dir:
        try:
            for i, m in enumerate(mutants, 1):
                tests = tests_for(root, m.path)
                if earlier.get(m.key) in ("killed", "timeout") or (
                        earlier.get(m.key) == "survived" and (args.merge or m.key in equivalent)):
                    status = earlier[m.key]    # carried over: tests were only added since
                    carried += 1
                    t0 = time.monotonic()
                elif args.report_only:
                    not_run.append(m.key)
                    continue
                else:
                    key = tuple(tests)
                    if key not in baseline:
                        baseline[key] = args.no_baseline or run_tests(root, tests, args.timeout) == "passed"
                    if not baseline[key]:
                        if m.path not in failed_baseline:
                            failed_baseline.append(m.path)
                        continue
                    t0 = time.monotonic()
                    status = run_mutant(root, m, tests, args.timeout, backup_dir)
                results.append((m, status))
                say(f"[{i}/{len(mutants)}] {status:8s} {time.monotonic() - t0:6.1f}s  {m.key}")
        except KeyboardInterrupt:
            interrupted = True
            print("interrupted; the mutated file was restored; partial report follows",
                  file=sys.stderr)
    say(f"# finished {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}"
        + (f"; {carried} results carried over "
           f"from {', '.join(args.rerun)} (0.0s lines)" if args.rerun else ""))
    say("")
    say(report(results, equivalent, failed_baseline))
    if not_run:
        say(f"not run ({len(not_run)}):")
        say("\n".join(f"  {k}" for k in not_run))
    if log:
        log.close()
    return 130 if interrupted else 0


if __name__ == "__main__":
    sys.exit(main())
