"""Every repository path that the docs, the README, the result files and the code's
docstrings and comments cite exists (issue 49: docs cited files that no longer
existed).

A citation is a path under one of the repository's top-level folders. Brace groups
expand (``benchmarks/results/x.{md,json}``); a path that stops at a placeholder
(``corpus_<variant>.md``, an f-string's ``{name}`` in code) or names an output stem
(``--out benchmarks/results/dense_profile``) counts when some file starts with it. A
file kept only in history is cited as ``git show COMMIT:path`` (the ``:`` before the
path keeps it out of this check).
"""
from __future__ import annotations

import itertools
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
TOP = ("benchmarks", "docs", "tests", "scenes", "mitsuba_plugins", "integrators", "media",
       ".ci")
#: a path under a top-level folder, not the tail of another path, URL or commit:path
CITATION = re.compile(r"(?<![\w/.:$<@-])((?:" + "|".join(re.escape(t) for t in TOP)
                      + r")/[A-Za-z0-9_./{},*-]*[A-Za-z0-9_}/])")


def _expand(path: str) -> list:
    m = re.search(r"\{([^{}]*)\}", path)
    if not m:
        return [path]
    return list(itertools.chain.from_iterable(
        _expand(path[:m.start()] + alt + path[m.end():]) for alt in m.group(1).split(",")))


def _sources() -> list:
    files = [ROOT / "README.md", ROOT / "scenes" / "README.md", *ROOT.glob("docs/*.md"),
             *ROOT.glob("benchmarks/results/*.md")]
    for folder in ("mitsuba_plugins", "integrators", "media", "benchmarks", "tests"):
        files += sorted((ROOT / folder).rglob("*.py"))
    return [f for f in files if f != Path(__file__).resolve()]   # its examples are made up


def _exists(path: str) -> bool:
    path = path.rstrip("/.")
    if (ROOT / path).exists():
        return True
    # a stem or a prefix before a placeholder: some file starts with it
    folder, _, stem = path.rpartition("/")
    return bool(stem) and (ROOT / folder).is_dir() and \
        any(p.name.startswith(stem) for p in (ROOT / folder).iterdir())


def test_every_cited_path_exists():
    missing = []
    for source in _sources():
        code = source.suffix == ".py"
        for n, line in enumerate(source.read_text(errors="replace").splitlines(), 1):
            for match in CITATION.finditer(line):
                cited = match.group(1)
                # in code, braces are f-string fields: keep what precedes the first
                paths = [cited.split("{", 1)[0]] if code else _expand(cited)
                for path in paths:
                    if "*" in path:
                        path = path.split("*", 1)[0]
                    if not _exists(path):
                        missing.append(f"{source.relative_to(ROOT)}:{n}: {path}")
    assert not missing, "cited paths that do not exist:\n" + "\n".join(missing)


def test_the_check_finds_a_missing_path():
    """The check can fail: a made-up citation is found and reported missing; a history
    citation (``git show COMMIT:path``) is not a citation; a stem counts."""
    line = ("see benchmarks/results/no_such_file.md and "
            "`git show 41d16df:mitsuba_plugins/adjoint.py`")
    found = [m.group(1) for m in CITATION.finditer(line)]
    assert found == ["benchmarks/results/no_such_file.md"]
    assert not _exists(found[0])
    assert _exists("benchmarks/results/inverse") and _exists("docs/usage.md")
    assert _expand("a/x.{md,json}") == ["a/x.md", "a/x.json"]
