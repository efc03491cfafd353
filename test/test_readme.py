"""
The README and the docs pages say what the code does.

Their Python blocks run as pasted (in order, one namespace per page, from the repository root;
where a block is followed by a text block and the words between them say it ``prints``, the
output must be that text); their `ctid` command lines parse; their module paths, files, links
and anchors exist; the README stays a front door; the real-data tables of the benchmarks page
are the ones their benchmark wrote. A block whose first line is ``# needs ROS 2`` runs only
where rclpy is installed.
"""

import importlib
from pathlib import Path
import re
import shlex
from typing import List, NamedTuple, Optional

from ctid_ros.cli.main import build_parser
from ctid_ros.streaming.params_file import load_params_file
import pytest

REPOSITORY = Path(__file__).resolve().parents[1]
README = (REPOSITORY / 'README.md').read_text(encoding='utf-8')
PAGES = ('README.md', 'docs/user-guide.md', 'docs/parameters.md', 'docs/benchmarks.md')
TEXTS = {page: (REPOSITORY / page).read_text(encoding='utf-8') for page in PAGES}
# What a reader sees: without the HTML comments (notes for the next editor).
VISIBLE = {page: re.sub(r'<!--.*?-->', '', text, flags=re.DOTALL) for page, text in TEXTS.items()}
MAX_README_LINES = 300


class Block(NamedTuple):
    """A fenced code block of a page."""

    language: str
    code: str
    line: int
    expected: Optional[str]     # the text block it prints, if the page shows one


def blocks(text: str) -> List[Block]:
    """Return the fenced blocks of ``text``, each Python block with the output it shows."""
    found = [(match.group(1), match.group(2), text.count('\n', 0, match.start()) + 1,
              match.start(), match.end())
             for match in re.finditer(r'^```(\w*)\n(.*?)^```$', text, re.DOTALL | re.MULTILINE)]
    result = []
    for index, (language, code, line, _, end) in enumerate(found):
        expected = None
        if language == 'python' and index + 1 < len(found):
            following = found[index + 1]
            if following[0] == 'text' and 'prints' in text[end:following[3]]:
                expected = following[1]
        result.append(Block(language, code, line, expected))
    return result


def resolves(dotted: str) -> bool:
    """Return True if ``dotted`` is a module or an attribute of one (``module.name``)."""
    parts = dotted.split('.')
    for split in range(len(parts), 0, -1):
        try:
            target = importlib.import_module('.'.join(parts[:split]))
        except ImportError:
            continue
        for name in parts[split:]:
            if not hasattr(target, name):
                return False
            target = getattr(target, name)
        return True
    return False


def slug(heading: str) -> str:
    """Return the anchor GitHub gives a heading."""
    return re.sub(r'[^\w\- ]', '', heading.strip().lower()).replace(' ', '-')


def anchors(text: str) -> set:
    """Return the anchors of the headings of a page (outside code blocks)."""
    outside = re.sub(r'^```.*?^```$', '', text, flags=re.DOTALL | re.MULTILINE)
    return {slug(heading) for heading in re.findall(r'^#+ (.*)$', outside, re.MULTILINE)}


def test_readme_is_a_front_door():
    assert README.count('\n') <= MAX_README_LINES
    for word in ('make demo', 'make test', 'docs/user-guide.md', 'docs/parameters.md',
                 'docs/benchmarks.md', 'docs/algorithm.md'):
        assert word in README, word
    kinds = [block.language for block in blocks(README)]
    assert kinds.count('python') >= 1 and kinds.count('sh') >= 3


@pytest.mark.parametrize('page', ['README.md', 'docs/user-guide.md'])
def test_python_blocks_run_as_pasted(page, monkeypatch, capsys):
    monkeypatch.chdir(REPOSITORY)
    namespace = {'__name__': '__main__'}
    ran = 0
    for block in blocks(TEXTS[page]):
        if block.language != 'python':
            continue
        if block.code.startswith('# needs ROS 2'):
            pytest.importorskip('rclpy')
        capsys.readouterr()
        exec(compile(block.code, f'{page}, line {block.line}', 'exec'), namespace)
        ran += 1
        if block.expected is not None:
            printed = capsys.readouterr().out
            assert printed == block.expected, \
                f'{page}, line {block.line}: the block now prints\n{printed}'
    assert ran >= 1


def command_lines(text: str) -> List[List[str]]:
    """Return the ``ctid`` command lines of the shell blocks, as argument lists."""
    lines = []
    for block in blocks(text):
        if block.language != 'sh':
            continue
        for command in block.code.replace('\\\n', ' ').splitlines():
            words = shlex.split(command, comments=True)
            # The command alone: up to a background &, a pipe, a redirection or a next command.
            for index, word in enumerate(words):
                if word in ('&', '&&', '|', ';', '>', '<'):
                    words = words[:index]
                    break
            if words and words[0].rsplit('/', 1)[-1] == 'ctid':
                lines.append(words[1:])
    return lines


@pytest.mark.parametrize('page', ['README.md', 'docs/user-guide.md'])
def test_ctid_command_lines_parse(page):
    lines = command_lines(TEXTS[page])
    assert lines
    parser = build_parser()
    for arguments in lines:
        try:
            parser.parse_args(arguments)
        except SystemExit:
            pytest.fail(f'{page}: ctid {shlex.join(arguments)} does not parse')


def test_params_files_written_by_the_readme_configure_a_node(tmp_path):
    files = re.findall(r"^cat > (\S+) <<'END'\n(.*?)^END$", README, re.DOTALL | re.MULTILINE)
    assert files
    for name, content in files:
        path = tmp_path / name
        path.write_text(content, encoding='utf-8')
        config = load_params_file(path)
        assert config.model, name


@pytest.mark.parametrize('dotted', sorted({dotted for text in VISIBLE.values()
                                           for dotted in re.findall(r'\bctid_ros(?:\.\w+)+',
                                                                    text)}))
def test_dotted_paths_resolve(dotted):
    assert resolves(dotted), dotted


@pytest.mark.parametrize('path', sorted({path for text in VISIBLE.values() for path in re.findall(
    r'\b((?:ctid_ros|test|config|docs|bench)/[\w./-]*\w/?)', text)}))
def test_paths_exist(path):
    assert (REPOSITORY / path).exists(), path


@pytest.mark.parametrize('page', PAGES)
def test_links_and_anchors_exist(page):
    outside = re.sub(r'^```.*?^```$', '', VISIBLE[page], flags=re.DOTALL | re.MULTILINE)
    for target in re.findall(r'\]\(([^)\s]+)\)', outside):
        if re.match(r'\w+://', target):
            continue
        path, _, anchor = target.partition('#')
        file = (REPOSITORY / page).parent / path if path else REPOSITORY / page
        assert file.exists(), f'{page}: link to {target}: no such file'
        if anchor:
            assert anchor in anchors(file.read_text(encoding='utf-8')), \
                f'{page}: link to {target}: no such heading'


def test_layout_names_every_module_outside_estimation():
    guide = TEXTS['docs/user-guide.md']
    layout = guide[guide.index('## Package layout'):guide.index('## References')]
    missing = sorted(str(path.relative_to(REPOSITORY)) for path in
                     (REPOSITORY / 'ctid_ros').glob('*/*.py')
                     if path.parent.name != 'estimation' and path.stem not in (
                         '__init__', '__main__') and f'`{path.name}`' not in layout
                     and f'/{path.name}`' not in layout)
    assert not missing, f'modules missing in the user guide layout: {missing}'


def test_commands_name_existing_modules_and_scripts():
    setup = (REPOSITORY / 'setup.py').read_text(encoding='utf-8')
    for text in TEXTS.values():
        for module in re.findall(r'python -m ([\w.]+)', text):
            assert importlib.util.find_spec(module) is not None, module
    for script in ('ctid', 'ctid_node', 'ctid_plant'):
        assert re.search(rf"'{script} = ctid_ros\.[\w.]+:main'", setup), script
        assert re.search(rf'\b{script}\b', README), script


def test_real_data_tables_are_those_their_benchmark_wrote():
    written = (REPOSITORY / 'bench' / 'results-real-data.md').read_text(encoding='utf-8')
    page = TEXTS['docs/benchmarks.md']
    begin, end = ('<!-- BEGIN bench/results-real-data.md -->\n',
                  '<!-- END bench/results-real-data.md -->')
    shown = page[page.index(begin) + len(begin):page.index(end)]
    assert shown.strip() == written.strip(), \
        'docs/benchmarks.md: copy bench/results-real-data.md (python -m bench real_data) ' \
        'between its markers'


def test_benchmarks_page_lists_every_benchmark_of_make_bench():
    from bench.__main__ import BENCHMARKS
    page = TEXTS['docs/benchmarks.md']
    missing = [name for name in BENCHMARKS if f'`bench/{name}.py`' not in page]
    assert not missing, f'benchmarks of make bench missing in docs/benchmarks.md: {missing}'
