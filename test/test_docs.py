"""The documentation site builds (MkDocs, warnings as errors); the README stays short."""

from pathlib import Path
import subprocess
import sys

import pytest

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.unit


def test_the_site_builds_with_warnings_as_errors(tmp_path):
    done = subprocess.run([sys.executable, '-m', 'mkdocs', 'build', '--strict', '-f',
                           str(REPO / 'docs' / 'mkdocs.yml'), '-d', str(tmp_path / 'site')],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    site = tmp_path / 'site'
    pages = {p.relative_to(site).as_posix() for p in site.rglob('*.html')}
    assert {'index.html', 'nodes/index.html', 'results/index.html'} <= pages


def test_the_readme_is_a_five_minute_read_whose_links_resolve():
    text = (REPO / 'README.md').read_text()
    assert len(text.splitlines()) <= 200
    for target in ('docs/pages/index.md', 'docs/pages/nodes.md', 'docs/pages/results.md',
                   'docs/pages/demo.png'):
        assert f']({target})' in text and (REPO / target).exists(), target
