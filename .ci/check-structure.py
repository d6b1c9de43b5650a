#!/usr/bin/env python3
"""The house rules that no compiler checks, checked on every CI run.

Each rule is one function returning a list of violations; the script prints
them all and exits 1 when there is any. Why a script: these rules (crates
depend only downward, no import circle between files, `super::` and
`self::` paths included, no file over 600 lines before its tests, the
server reads no weight metadata by string key, one `Sex`, a short model
card, no work-log references, no registry host, no test hidden behind
`test = false` or `doctest = false`) decay silently when nobody
looks; a failing CI line is what keeps them.
"""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# Layers, bottom up: a crate may depend only on crates of a lower layer.
LAYERS = {
    "blapose-core": 0,
    "blapose-data": 1,
    "blapose-model": 1,
    "blapose-proto": 1,
    "blapose-lifters": 1,
    "blapose-export": 1,
    "blapose-tls": 1,
    "blapose-train": 2,
    "blapose-server": 2,
    "blapose-client": 2,
    "blapose-examples": 2,
    "blapose-lab": 3,
    "blapose-test-support": 3,
    "blapose-bench": 4,
    "blapose-tests": 4,
}
MAX_CYCLE_FILES = 1
MAX_SOURCE_LINES = 600
MAX_MODEL_CARD_LINES = 300
WORK_LOG = re.compile(r"(?<![-\w])(sessions? \d+(\s*(-|–|to|and)\s*\d+)?\b|work period|session-\d+)", re.I)
# Package registries and mirrors: the machine's own configuration names them.
REGISTRY_HOST = re.compile(
    r"(deb\.debian\.org|security\.debian\.org|ftp\.[a-z.]*debian\.org|archive\.ubuntu\.com|"
    r"pypi\.org|files\.pythonhosted\.org|crates\.io|registry\.npmjs\.org|mirrors?\.[a-z0-9.-]+\.[a-z]+)",
    re.I,
)


def tracked_files():
    out = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard"],
        cwd=ROOT, check=True, capture_output=True, text=True,
    ).stdout
    return [ROOT / p for p in out.splitlines() if (ROOT / p).is_file()]


def manifests():
    for path in sorted(ROOT.glob("**/Cargo.toml")):
        if "target" in path.parts or path.parent == ROOT:
            continue
        text = path.read_text()
        name = re.search(r'^name\s*=\s*"([^"]+)"', text, re.M)
        if name:
            yield path, name.group(1), text


def crate_layers():
    problems = []
    for path, name, text in manifests():
        if name not in LAYERS:
            problems.append(f"{path.relative_to(ROOT)}: crate {name} has no layer in .ci/check-structure.py")
            continue
        deps = text.split("[dev-dependencies]")[0]
        for dep in sorted(set(re.findall(r"^(blapose-[a-z-]+)", deps, re.M))):
            if dep in LAYERS and LAYERS[dep] >= LAYERS[name]:
                problems.append(f"{name} depends on {dep}, which is not below it")
    return problems


def rust_sources(crate_dir):
    src = crate_dir / "src"
    return sorted(p for p in src.rglob("*.rs")) if src.is_dir() else []


def module_of(src, path):
    rel = path.relative_to(src).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] in ("mod", "lib", "main"):
        parts = parts[:-1]
    return tuple(parts)


def import_cycles():
    problems = []
    for path, name, _ in manifests():
        src = path.parent / "src"
        files = [f for f in rust_sources(path.parent) if "bin" not in f.relative_to(src).parts]
        modules = {module_of(src, f): f for f in files}
        edges = {f: set() for f in files}
        for mod, f in modules.items():
            code = "\n".join(l for l in strip_tests(f.read_text()).splitlines() if not l.lstrip().startswith("//"))
            refs = [tuple(r.strip(":").split("::")) for r in re.findall(r"\bcrate((?:::[a-z_][a-z0-9_]*)+)", code)]
            # `super::x` and `self::x` name modules relative to this one
            for base, ref in re.findall(r"\b(super|self)((?:::[a-z_][a-z0-9_]*)+)", code):
                here = mod[:-1] if base == "super" else mod
                refs.append(here + tuple(ref.strip(":").split("::")))
            for parts in refs:
                # the longest module prefix of the path is the file it names
                for k in range(len(parts), 0, -1):
                    target = modules.get(parts[:k])
                    if target is not None:
                        if target != f:
                            edges[f].add(target)
                        break
        for component in strongly_connected(edges):
            if len(component) > MAX_CYCLE_FILES:
                names = ", ".join(sorted(str(c.relative_to(ROOT)) for c in component))
                problems.append(f"{name}: import circle of {len(component)} files: {names}")
    return problems


def strongly_connected(edges):
    index, low, stack, on_stack, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            out.append(component)

    sys.setrecursionlimit(10000)
    for v in edges:
        if v not in index:
            visit(v)
    return out


def strip_tests(text):
    """The file before its `#[cfg(test)]` module (what counts as its source)."""
    match = re.search(r"^#\[cfg\(test\)\]\s*\n\s*(pub(\([a-z]+\))? )?mod ", text, re.M)
    return text[: match.start()] if match else text


def file_sizes():
    problems = []
    for path, name, _ in manifests():
        for f in rust_sources(path.parent):
            lines = strip_tests(f.read_text()).count("\n")
            if lines > MAX_SOURCE_LINES:
                problems.append(f"{f.relative_to(ROOT)}: {lines} lines before its tests (at most {MAX_SOURCE_LINES})")
    return problems


def server_metadata_keys():
    problems = []
    for f in sorted((ROOT / "server" / "src").rglob("*.rs")):
        for n, line in enumerate(f.read_text().splitlines(), 1):
            if re.search(r"\.extra\s*\.\s*get\(|train_config", line):
                problems.append(f"{f.relative_to(ROOT)}:{n}: the server reads weight metadata by key: {line.strip()}")
    return problems


def one_sex():
    found = []
    for f in tracked_files():
        if f.suffix == ".rs" and "target" not in f.parts:
            for n, line in enumerate(f.read_text().splitlines(), 1):
                if re.match(r"\s*pub\s+enum\s+Sex\b|\s*enum\s+Sex\b", line):
                    found.append(f"{f.relative_to(ROOT)}:{n}")
    return [] if len(found) <= 1 else [f"`enum Sex` is defined {len(found)} times: {', '.join(found)}"]


def model_card():
    lines = (ROOT / "models" / "README.md").read_text().count("\n")
    return [] if lines <= MAX_MODEL_CARD_LINES else [f"models/README.md has {lines} lines (at most {MAX_MODEL_CARD_LINES})"]


TEXT_SUFFIXES = {".rs", ".md", ".proto", ".py", ".sh", ".toml", ".yaml", ".yml", ".cfg", ".txt", ".html", ".js", ".pyi", ""}


def text_lines(skip):
    for f in tracked_files():
        rel = f.relative_to(ROOT)
        if f.suffix not in TEXT_SUFFIXES or str(rel) in skip or f.stat().st_size > 2_000_000:
            continue
        try:
            text = f.read_text()
        except UnicodeDecodeError:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            yield rel, n, line


def work_logs():
    skip = {"docs/research.md", ".ci/check-structure.py"}
    return [f"{rel}:{n}: work-log reference: {line.strip()[:120]}" for rel, n, line in text_lines(skip) if WORK_LOG.search(line)]


def registry_hosts():
    skip = {"Cargo.lock", ".ci/check-structure.py"}
    return [f"{rel}:{n}: names a registry or mirror host: {line.strip()[:120]}" for rel, n, line in text_lines(skip) if REGISTRY_HOST.search(line)]


UNIT_TEST = re.compile(r"#\[(tokio::)?test\b|#\[cfg\(test\)\]")
DOC_FENCE = re.compile(r"^\s*//[/!]\s*```\s*(\S*)")


def doc_examples(path):
    """Rust code blocks in a file's doc comments (what rustdoc would test)."""
    found, inside = [], False
    for n, line in enumerate(path.read_text().splitlines(), 1):
        m = DOC_FENCE.match(line)
        if not m:
            continue
        if not inside and (m.group(1) == "" or re.search(r"rust|no_run|should_panic|compile_fail|edition", m.group(1))):
            found.append(n)
        inside = not inside
    return found


def bin_modules(main):
    """A binary's root file and the module files it declares (`mod x;`),
    recursively, looked up beside it as `x.rs` or `x/mod.rs`."""
    files, todo = [], [main]
    while todo:
        f = todo.pop()
        if not f.exists() or f in files:
            continue
        files.append(f)
        base = f.parent if f.name in ("main.rs", "mod.rs") else f.with_suffix("")
        for m in re.findall(r"^\s*(?:pub(?:\([^)]*\))?\s+)?mod\s+(\w+)\s*;", f.read_text(), re.M):
            todo += [base / f"{m}.rs", base / m / "mod.rs"]
    return files


def untested_targets():
    """`test = false` or `doctest = false` (set so `cargo test` skips empty
    harnesses) must not hide a test someone adds later."""
    import tomllib

    problems = []
    for path, name, text in manifests():
        crate = path.parent
        manifest = tomllib.loads(text)
        lib = manifest.get("lib", {})
        lib_file = crate / lib.get("path", "src/lib.rs")
        bins = manifest.get("bin", [])
        bin_files = [crate / b.get("path", f"src/bin/{b['name']}.rs") for b in bins]
        lib_sources = [p for p in rust_sources(crate) if p not in bin_files and "bin" not in p.relative_to(crate / "src").parts[:1] and p.name != "main.rs"]
        checks = []
        if lib_file.exists() and lib.get("test") is False:
            checks += [(p, "test") for p in lib_sources]
        if lib_file.exists() and lib.get("doctest") is False:
            checks += [(p, "doctest") for p in lib_sources]
        for b, f in zip(bins, bin_files):
            if b.get("test") is False:
                checks += [(p, "test") for p in bin_modules(f)]
        for p, kind in checks:
            rel = p.relative_to(ROOT)
            if kind == "test" and UNIT_TEST.search(p.read_text()):
                problems.append(f"{rel}: has unit tests, but its target in {path.relative_to(ROOT)} says test = false")
            if kind == "doctest":
                for n in doc_examples(p):
                    problems.append(f"{rel}:{n}: a doc example, but {path.relative_to(ROOT)} says doctest = false")
    return problems


RULES = [crate_layers, import_cycles, file_sizes, server_metadata_keys, one_sex, model_card, work_logs, registry_hosts, untested_targets]


def main():
    problems = [(rule.__name__, p) for rule in RULES for p in rule()]
    for rule, p in problems:
        print(f"{rule}: {p}")
    print(f"check-structure: {len(RULES)} rules, {len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
