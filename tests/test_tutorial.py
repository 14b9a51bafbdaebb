"""The documentation as a user meets it: the site builds strict (a broken link fails it), every extension point's
docstring is on the site, and the tutorial's and the troubleshooting page's commands run as written.

Blocks are taken from the pages themselves: a fenced ``bash`` block after ``<!-- tutorial ... -->`` (with
``expect="TEXT"``: its output holds TEXT; ``expect-file="PATH"``: it leaves PATH), a ``console`` block after
``<!-- troubleshoot exit=N -->`` (its ``$`` lines run in order; the last exits N and prints the lines shown).
They run in a fresh folder standing for the repository's root (``scenarios/`` and ``docs/`` linked in), with the
venv's console scripts first on PATH and the pages' loopback ports swapped for free ones.
"""

from __future__ import annotations

import html
import importlib
import inspect
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

DOCS = ROOT / "docs"
TUTORIAL = re.compile(r"<!-- tutorial(?P<attrs>[^>]*)-->\n```bash\n(?P<body>.*?)```", re.S)
TROUBLE = re.compile(r"<!-- troubleshoot exit=(?P<exit>\d+) -->\n```console\n(?P<body>.*?)```", re.S)
PORTS = ("7447", "8765")  # the pages' loopback ports


def _mkdocs(config: Path, site: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, NO_MKDOCS_2_WARNING="1")
    return subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(site)],
                          capture_output=True, text=True, timeout=300, env=env)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("site")
    p = _mkdocs(ROOT / "mkdocs.yml", out)
    assert p.returncode == 0, f"mkdocs build --strict failed:\n{p.stderr[-3000:]}"
    return out


def test_the_site_builds_strict_with_every_page_in_its_navigation(site):
    pages = {p.stem for p in DOCS.glob("*.md")}
    assert {"index", "tutorial", "troubleshooting", "api", "settings"} <= pages
    for stem in pages - {"index"}:
        assert (site / stem / "index.html").exists(), f"docs/{stem}.md is not on the site"


def test_a_broken_link_fails_the_strict_build(tmp_path):
    shutil.copytree(DOCS, tmp_path / "docs")
    shutil.copy(ROOT / "mkdocs.yml", tmp_path / "mkdocs.yml")
    page = tmp_path / "docs" / "tutorial.md"
    page.write_text(page.read_text() + "\nSee [the missing page](no-such-page.md) and [an anchor](index.md#nowhere).\n")
    p = _mkdocs(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert p.returncode != 0
    assert "no-such-page.md" in p.stderr and "nowhere" in p.stderr


def _objects() -> list[str]:
    return re.findall(r"^::: (\S+)$", (DOCS / "api.md").read_text(), re.M)


def _resolve(path: str):
    mod, _, name = path.rpartition(".")
    return getattr(importlib.import_module(mod), name)


def _first_words(doc: str) -> str:
    """The docstring's first line as the site shows it (rst literals as plain text), its first eight words."""
    line = inspect.cleandoc(doc).splitlines()[0]
    line = re.sub(r":\w+:`", "`", line)
    line = re.sub(r"`+", "", line)
    return "".join(line.split()[:8])  # compared without spaces: the site puts tags where the docstring had none


def _text(html_page: str) -> str:
    return "".join(html.unescape(re.sub(r"<[^>]+>", "", html_page)).split())


def test_every_extension_point_has_its_docstring_on_the_site(site):
    objects = _objects()
    for needed in ("stack.drivers.base.Driver", "stack.policies.base.Policy", "stack.drivers.lidar.Lidar",
                   "stack.plugins.Plugin", "stack.agents.step.StepPipeline", "stack.scenario.Scenario"):
        assert needed in objects, f"docs/api.md does not render {needed}"
    text = _text((site / "api" / "index.html").read_text())
    for path in objects:
        obj = _resolve(path)
        assert obj.__doc__ and obj.__doc__.strip(), f"{path} has no docstring"
        assert _first_words(obj.__doc__) in text, f"{path}'s docstring is not on the site's API page"
    roles = sorted(set(re.findall(r":(?:class|func|meth|attr|data|mod):\w", text)))
    assert not roles, f"Sphinx roles show raw on the site's API page (write ``name``): {roles}"
    for base in ("stack.drivers.base.Driver", "stack.policies.base.Policy", "stack.drivers.lidar.Lidar"):
        for name in getattr(_resolve(base), "__abstractmethods__", ()):  # what a plugin must write
            fn = getattr(_resolve(base), name)
            assert fn.__doc__, f"{base}.{name} (abstract) has no docstring"
            assert _first_words(fn.__doc__) in text, f"{base}.{name}'s docstring is not on the site"


def _workdir(tmp: Path) -> tuple[Path, dict, dict]:
    from stack.comm.session import free_tcp_endpoint

    for name in ("scenarios", "docs"):
        (tmp / name).symlink_to(ROOT / name)
    (tmp / "runs").mkdir()
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
               PYTHONUNBUFFERED="1")
    ports = {p: free_tcp_endpoint().rsplit(":", 1)[1] for p in PORTS}
    return tmp, env, ports


def _swap_ports(body: str, ports: dict) -> str:
    for old, new in ports.items():
        body = body.replace(f"127.0.0.1:{old}", f"127.0.0.1:{new}")
    return body


@pytest.mark.fleet
def test_the_tutorial_runs_as_written(tmp_path):
    blocks = list(TUTORIAL.finditer((DOCS / "tutorial.md").read_text()))
    assert len(blocks) == 5, "the tutorial is five steps, each one marked block"
    cwd, env, ports = _workdir(tmp_path)
    for n, m in enumerate(blocks, 1):
        attrs = dict(re.findall(r'([\w-]+)="([^"]*)"', m["attrs"]))
        p = subprocess.run(["bash", "-euo", "pipefail", "-c", _swap_ports(m["body"], ports)], cwd=cwd, env=env,
                           capture_output=True, text=True, timeout=300)
        said = p.stdout + p.stderr
        assert p.returncode == 0, f"tutorial step {n} exited {p.returncode}:\n{said[-3000:]}"
        if "expect" in attrs:
            assert attrs["expect"] in said, f"tutorial step {n} did not print {attrs['expect']!r}:\n{said[-3000:]}"
        if "expect-file" in attrs:
            assert (cwd / attrs["expect-file"]).stat().st_size > 0, f"tutorial step {n} left no {attrs['expect-file']}"
    assert "Traceback" not in said


def test_the_troubleshooting_page_shows_what_the_tools_print(tmp_path):
    blocks = list(TROUBLE.finditer((DOCS / "troubleshooting.md").read_text()))
    assert len(blocks) >= 5
    cwd, env, ports = _workdir(tmp_path)
    for m in blocks:
        lines = m["body"].rstrip("\n").splitlines()
        cmds = [ln[2:] for ln in lines if ln.startswith("$ ")]
        shown = [ln for ln in lines if not ln.startswith("$ ")]
        for cmd in cmds[:-1]:
            subprocess.run(["bash", "-c", cmd], cwd=cwd, env=env, check=True, timeout=60)
        p = subprocess.run(["bash", "-c", _swap_ports(cmds[-1], ports)], cwd=cwd, env=env, capture_output=True,
                           text=True, timeout=120)
        said = p.stdout + p.stderr
        assert p.returncode == int(m["exit"]), f"{cmds[-1]!r} exited {p.returncode}, the page says {m['exit']}"
        for line in shown:
            assert _swap_ports(line, ports) in said, f"{cmds[-1]!r} no longer prints {line!r}:\n{said[-2000:]}"
        assert "Traceback" not in said


def test_every_figure_in_the_docs_is_made_by_one_command(capsys):
    """``make figures`` (bench/figures.py): the registry against the folders, and every script it runs exists."""
    sys.path.insert(0, str(ROOT / "bench"))
    try:
        import figures
    finally:
        sys.path.remove(str(ROOT / "bench"))
    pictures = {f"figures/{p.name}" for p in (DOCS / "figures").iterdir() if p.suffix in (".png", ".gif")}
    pictures |= {p.name for p in DOCS.glob("*.png")}
    assert set(figures.made()) == pictures
    for fig in figures.FIGURES:
        for cmd in fig.commands:
            scripts = [c for c in cmd if c.endswith((".py", ".sh")) and not c.startswith("-")]
            assert all((ROOT / c).exists() for c in scripts), f"{fig.name}: {scripts}"
    assert figures.main(["--list"]) == 0 and "bench/heldout.py" in capsys.readouterr().out
    assert figures.main(["--only", "no-such.png"]) == 2
