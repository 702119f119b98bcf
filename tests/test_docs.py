"""The repository documents itself: no tracked file cites a document or a path that is not
in the repository, and every relative Markdown link (and its #anchor) resolves."""

from __future__ import annotations

import re
import shutil
import subprocess
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

# Written in pieces so that this file does not match itself.
_OUTSIDE = re.compile("|".join([
    r"DESIGN" + r"\.md",
    r"SEEDS" + r"\.md",
    r"STYLE" + r"\.md",
    r"(?<![\w.-])shared" + r"/",
    r"(?<![\w.-])seeds" + r"/",
    r"/wo" + r"rk/",
]))


def _tracked() -> list[Path]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    return [ROOT / p for p in out.decode().split("\0") if p]


def _text(path: Path) -> str | None:
    try:
        data = path.read_bytes()
    except OSError:  # listed by git but deleted in the work tree
        return None
    if b"\0" in data[:8192]:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def test_no_reference_outside_the_repository():
    hits = []
    for path in _tracked():
        if path == Path(__file__).resolve():
            continue
        text = _text(path)
        if text is None:
            continue
        for n, line in enumerate(text.splitlines(), 1):
            if _OUTSIDE.search(line):
                hits.append(f"{path.relative_to(ROOT)}:{n}: {line.strip()[:100]}")
    assert not hits, "references to files outside the repository:\n" + "\n".join(hits)


def test_the_pattern_catches_what_it_must():
    # the guard above is only as good as its pattern
    for bad in ["see DESIGN" ".md", "(SEEDS" ".md §2)", "/wo" "rk/sh" "ared/DESIGN", "the originals in seeds" "/"]:
        assert _OUTSIDE.search(bad), bad
    for good in ["docs/design.md", "docs/algorithms.md", "process_rng(seed, ...)", "sensors_sim/README.md"]:
        assert not _OUTSIDE.search(good), good


# ---------------------------------------------------------------- Markdown links

_FENCE = re.compile(r"^(```|~~~).*?^\1", re.S | re.M)
_CODE = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_HEADING = re.compile(r"^#{1,6}\s+(.*?)\s*#*\s*$", re.M)
_ANCHOR = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"", re.I)


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # a link keeps its text
    text = unicodedata.normalize("NFC", text).lower()
    text = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LN")
    return text.replace(" ", "-")


def anchors(markdown: str) -> set[str]:
    body = _FENCE.sub("", markdown)
    seen: dict[str, int] = {}
    out = set(_ANCHOR.findall(markdown))
    for h in _HEADING.findall(body):
        s = _slug(h)
        k = seen.get(s, 0)
        seen[s] = k + 1
        out.add(s if k == 0 else f"{s}-{k}")
    return out


def links(markdown: str) -> list[str]:
    body = _CODE.sub("", _FENCE.sub("", markdown))
    return _LINK.findall(body)


def _markdown_files() -> list[Path]:
    return sorted(p for p in _tracked() if p.suffix == ".md" and p.exists())


def test_slug_rule():
    assert _slug("Time and determinism") == "time-and-determinism"
    assert _slug("`fusion/df/multi.py`") == "fusiondfmultipy"
    assert _slug("MEKF, the cross-fed filters") == "mekf-the-cross-fed-filters"
    assert anchors("# A\n## A\n```\n# not a heading\n```\n") == {"a", "a-1"}
    assert links("[x](a.md) `[y](b.md)` ![p](c.png)\n```\n[z](d.md)\n```") == ["a.md", "c.png"]


@pytest.mark.parametrize("doc", ["README.md", "docs/README.md", "docs/design.md", "docs/algorithms.md"])
def test_the_documents_exist(doc):
    assert (ROOT / doc).is_file(), doc


def test_every_relative_link_resolves():
    broken = []
    for md in _markdown_files():
        text = md.read_text(encoding="utf-8")
        for target in links(text):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, https:, mailto:
                continue
            path, _, anchor = target.partition("#")
            dest = (md.parent / path).resolve() if path else md
            where = f"{md.relative_to(ROOT)}: ({target})"
            if ROOT not in dest.parents and dest != ROOT:
                broken.append(f"{where}: outside the repository")
            elif not dest.exists():
                broken.append(f"{where}: no such file")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest.read_text(encoding="utf-8")):
                broken.append(f"{where}: no heading #{anchor}")
    assert not broken, "broken links:\n" + "\n".join(broken)
