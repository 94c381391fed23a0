"""mkdocs hook: the repository's own Markdown in the site, and links that leave docs/.

Some pages live where the code they describe lives (HARDWARE.md, ARCHITECTURE.md, daemon/PROTOCOL.md,
sssphase_core/SESSION_FORMAT.md, the README, the benchmark results in benchmarks/). They stay there
(other files and tools link to them) and a docs page pulls one in with an include marker on a line of
its own::

    <!-- include: HARDWARE.md -->
    <!-- include: HARDWARE.md until "## Writing a device plugin" -->
    <!-- include: HARDWARE.md from "## Writing a device plugin" -->

(``from`` starts after that heading, ``until`` stops before it). The benchmark results are served as
they are under ``results/`` (Markdown as pages, figures, JSON and scripts as files).

Links are written as the repository's relative paths, so they also work when browsing the files in a
checkout or a forge. Each link is resolved from the file that holds it (the included file for included
text) and rewritten to where its target is in the site: docs/ pages as they are, the files above to the
page that carries them, benchmarks/* to results/*. A link to any other file of the repository (source
code, a folder) becomes its path as code text; a link to a file that does not exist is left alone, so
``mkdocs build --strict`` reports it.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

PAGES = {  # repository path outside docs/ -> the site page that carries it
    "README.md": "index.md",
    "HARDWARE.md": "rig.md",
    "ARCHITECTURE.md": "architecture.md",
    "daemon/PROTOCOL.md": "protocol.md",
    "sssphase_core/SESSION_FORMAT.md": "session-format.md",
    "examples/sssphase-example-plugin": "plugins.md",
    "examples/sssphase-example-plugin/README.md": "plugins.md",
    "benchmarks": "results/index.md",
}
ANCHORS = {  # (repository path, anchor) carried by another page than PAGES says
    ("HARDWARE.md", "writing-a-device-plugin"): "plugins.md",
}
RESULTS_DIR = "benchmarks"  # served as results/
RESULTS = "results"

INCLUDE = re.compile(r'^<!--\s*include:\s*(\S+)(?:\s+(from|until)\s+"([^"]+)")?\s*-->\s*$', re.M)
LINK = re.compile(r'(!?)\[((?:[^\[\]]|\[[^\]]*\])*)\]\(([^)\s]+)((?:\s+"[^"]*")?)\)')
FENCE = re.compile(r"^\s*(```|~~~)")

_root = Path(".")
_sources: dict[str, str] = {}  # generated page -> its repository path


def on_config(config):
    global _root
    _root = Path(config.config_file_path).resolve().parent
    return config


def on_files(files, config):
    from mkdocs.structure.files import File

    results = sorted(p for p in (_root / RESULTS_DIR).iterdir() if p.is_file() and not p.name.startswith("."))
    index = [
        "# Benchmark results",
        "",
        "The files the benchmark commands write, as committed in `benchmarks/`; each benchmark page",
        "quotes them and names the command that writes them.",
        "",
    ]
    for path in results:
        src_uri = f"{RESULTS}/{path.name}"
        if path.suffix == ".md":
            _sources[src_uri] = f"{RESULTS_DIR}/{path.name}"
            body = path.read_text(encoding="utf-8")
            if not body.lstrip().startswith("# "):
                body = f"# {RESULTS_DIR}/{path.name}\n\n{body}"
            files.append(File.generated(config, src_uri, content=body))
        else:
            files.append(File.generated(config, src_uri, abs_src_path=str(path)))
        index.append(f"* [`{RESULTS_DIR}/{path.name}`]({path.name})")
    files.append(File.generated(config, f"{RESULTS}/index.md", content="\n".join(index) + "\n"))
    return files


def _section(text: str, mode: str | None, heading: str | None, name: str) -> str:
    if mode is None:
        return text
    lines = text.splitlines(keepends=True)
    at = [i for i, line in enumerate(lines) if line.rstrip() == heading]
    if not at:
        raise ValueError(f"include: {name} has no heading {heading!r}")
    return "".join(lines[at[0] + 1 :] if mode == "from" else lines[: at[0]])


def _target(resolved: str, anchor: str) -> tuple[str | None, str]:
    """(site src_uri or None, anchor) for a repository path."""
    bare = resolved.rstrip("/")
    if bare.startswith("docs/"):
        return bare[len("docs/") :], anchor
    if (bare, anchor) in ANCHORS:
        return ANCHORS[(bare, anchor)], ""
    if bare in PAGES:
        return PAGES[bare], anchor
    if bare.startswith(RESULTS_DIR + "/") and (_root / bare).is_file():
        return RESULTS + bare[len(RESULTS_DIR) :], anchor
    return None, anchor


def rewrite_links(text: str, base_dir: str, page_uri: str) -> str:
    """Links in ``text`` (held by a file in repository folder ``base_dir``) made right for ``page_uri``."""
    page_dir = posixpath.dirname(page_uri)

    def one(match: re.Match) -> str:
        bang, label, url, title = match.groups()
        if re.match(r"^[a-z][a-z0-9+.-]*:", url) or url.startswith(("#", "/")):
            return match.group(0)
        path, _, anchor = url.partition("#")
        resolved = posixpath.normpath(posixpath.join(base_dir, path)) + ("/" if path.endswith("/") else "")
        if resolved.startswith("../"):
            return match.group(0)
        site, anchor = _target(resolved, anchor)
        if site is not None:
            new = posixpath.relpath(site, page_dir or ".") + (f"#{anchor}" if anchor else "")
            return f"{bang}[{label}]({new}{title})"
        if bang or not (_root / resolved).exists():
            return match.group(0)  # an image outside the site or a missing file: --strict says so
        plain = label.strip("`").rstrip("/")
        shown = resolved.rstrip("/") + ("/" if (_root / resolved).is_dir() else "")
        if plain in (resolved.rstrip("/"), path.rstrip("/"), posixpath.basename(resolved.rstrip("/"))):
            return f"`{shown}`"
        return f"{label} (`{shown}`)"

    out, in_fence = [], False
    for line in text.splitlines(keepends=True):
        if FENCE.match(line):
            in_fence = not in_fence
        out.append(line if in_fence else LINK.sub(one, line))
    return "".join(out)


def on_page_markdown(markdown, page, config, files):
    src_uri = page.file.src_uri
    docs_rel = Path(config.docs_dir).resolve().relative_to(_root).as_posix()
    own = _sources.get(src_uri, f"{docs_rel}/{src_uri}")
    base = posixpath.dirname(own)

    pieces, last = [], 0
    for match in INCLUDE.finditer(markdown):
        pieces.append(rewrite_links(markdown[last : match.start()], base, src_uri))
        name, mode, heading = match.groups()
        text = _section((_root / name).read_text(encoding="utf-8"), mode, heading, name)
        pieces.append(rewrite_links(text, posixpath.dirname(name), src_uri))
        last = match.end()
    pieces.append(rewrite_links(markdown[last:], base, src_uri))
    return "".join(pieces)
