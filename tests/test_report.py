"""`frodo report`: evaluation sets reconstructed offline, scored and rendered into one page with its provenance;
stored results are reused on the same commit, a failing bag is named on the page and in the exit code."""
import subprocess
from pathlib import Path

import pytest

from frodo_bringup import report as report_module
from frodo_bringup.cli import main as frodo
from frodo_bringup.report import REPORT_SETS, ReportSet, commit_key, report
from frodo_bringup.testing import FAST_OPTIM_PARAMS as FAST

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture()
def in_repo(monkeypatch):
    monkeypatch.chdir(REPO)   # the sets read bags/ relative to the checkout, as `frodo report` does


def test_demo_set_is_reconstructed_scored_rendered_and_then_reused(tmp_path, in_repo):
    params = tmp_path / 'fast.yaml'
    params.write_text(FAST)
    page, work, lines = tmp_path / 'docs' / 'results.md', tmp_path / 'work', []
    assert report(['demo'], page=page, work=work, params=[params], limit=1, log=lines.append, commit='c0ffee') == []
    text = page.read_text()
    assert 'from results computed at commit `c0ffee` (page rendered at' in text and 'cores' in text and 'GPU:' in text
    row = next(line for line in text.splitlines() if line.startswith('| demo_walk |'))
    cells = [c.strip() for c in row.strip('|').split('|')]
    assert cells[1:4] == ['4', '4', '0']                       # objects, found, false positives
    assert float(cells[5]) < 5.0                                 # mean CD (cm) of the four objects
    assert 50.0 < float(cells[7]) <= 100.0                       # mean COMP@5cm (%)
    assert (page.parent / 'results' / 'demo.png').stat().st_size > 10_000
    assert '![demo: demo_walk](results/demo.png)' in text
    assert any('reconstructing' in line for line in lines)
    lines.clear()
    report(['demo'], page=page, work=work, params=[params], limit=1, log=lines.append, commit='c0ffee')
    assert any('stored result reused' in line for line in lines) and page.read_text() == text


def test_results_are_keyed_by_commit_and_by_the_uncommitted_diff(tmp_path):
    git = lambda *args: subprocess.run(['git', *args], cwd=tmp_path, check=True, capture_output=True)  # noqa: E731
    git('init', '-q')
    (tmp_path / 'a.txt').write_text('one\n')
    git('add', 'a.txt')
    git('-c', 'user.name=t', '-c', 'user.email=t@t', 'commit', '-q', '-m', 'one')
    clean = commit_key(tmp_path)
    assert len(clean) == 10 and '-' not in clean
    (tmp_path / 'a.txt').write_text('two\n')
    dirty = commit_key(tmp_path)
    assert dirty.startswith(clean + '-dirty-') and commit_key(tmp_path) == dirty
    (tmp_path / 'a.txt').write_text('three\n')
    assert commit_key(tmp_path) not in (clean, dirty)
    assert commit_key(tmp_path / 'nowhere') == 'unknown'


def test_a_failing_bag_is_named_and_gives_exit_code_1(tmp_path, in_repo, monkeypatch, capsys):
    broken = tmp_path / 'broken.mcap'
    broken.write_bytes(b'not a bag')
    monkeypatch.setitem(REPORT_SETS, 'broken', ReportSet('broken', 'Broken', 'A file that is no bag.',
                                                         lambda work: [broken]))
    page = tmp_path / 'results.md'
    code = frodo(['report', '--sets', 'broken', '--page', str(page), '--work', str(tmp_path / 'work')])
    assert code == 1
    assert 'frodo report: failed: broken/broken:' in capsys.readouterr().err
    assert '| broken | - | - | - | - | - | - | - | failed:' in page.read_text()


def test_a_set_without_bags_says_how_to_make_them(tmp_path, in_repo, monkeypatch):
    monkeypatch.setattr(report_module, 'PUBLIC_REAL_DIR', tmp_path / 'absent')
    page = tmp_path / 'results.md'
    assert report(['public-real'], page=page, work=tmp_path / 'work', log=lambda line: None) == []
    assert 'No bags: not built here: run `scripts/build_real_bags.sh`' in page.read_text()


def test_unknown_sets_are_refused(tmp_path, capsys):
    assert frodo(['report', '--sets', 'nope', '--page', str(tmp_path / 'r.md')]) == 2
    assert "unknown set(s) nope" in capsys.readouterr().err
