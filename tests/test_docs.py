"""The examples in README.md and docs/*.md run, so the documentation stays true.

Conventions for writers of the docs (every Markdown file in docs/ is picked up
automatically, e.g. docs/api.md):

- A fenced block tagged ``console`` is executed. Each line starting with ``$ armfit`` is
  a command (a trailing ``\\`` continues it on the next line); the lines after it, up to
  the next ``$``, are its output as a user sees it (stdout and stderr). Commands run
  in-process through click's CliRunner, with no shell: no pipes, redirections or
  variables. Every ``$`` line of a ``console`` block must be an ``armfit`` command; use
  ``sh`` for illustrations that are not run (paths such as ``raw/`` that a user has but
  the repository does not).
- A command must exit 0, unless it ends with a comment ``# exit N`` (then it must exit N).
- ``console check``: the output shown is compared with the real output (only on the
  locked versions of requirements.lock: an optimiser's digits may differ on another
  set). Each shown line must match a real line, in order (real lines may be left out
  in the doc: a trimmed output is fine); text must be equal up to runs of spaces, and
  each number must agree within 5 % or two units of its last shown digit. A line
  starting with ``…`` marks an elision and is not compared. Without ``check`` the output
  is not compared.
- ``python``: the block is executed with ``exec`` (blocks of one file share a namespace,
  in order).
- ``slow`` (e.g. ``console slow``, ``console check slow``, ``python slow``): a heavy
  example, skipped unless the environment variable ``ARMFIT_DOCS_SLOW=1`` is set. Later
  blocks must not depend on a slow block's files.
- ``skip``: a block of one of the languages above that is shown but never run.

Every file's examples run in a fresh temporary folder that holds links to
``sample_data/`` and ``examples/``, so paths are written as from the repository root
(``sample_data/study``) and outputs land in the temporary folder. A command run with the
same arguments on the same input files (e.g. ``armfit estimate sample_data/study -o
study/spectra.parquet`` in two files) runs once per session: its files and output are
replayed afterwards.
"""

from __future__ import annotations

import hashlib
import os
import re
import shlex
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from click.testing import CliRunner
from locked import unlocked

from armfit.cli.main import cli

ROOT = Path(__file__).resolve().parents[1]
DOCS = [p for p in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))] if p.is_file()]
RUN_SLOW = os.environ.get("ARMFIT_DOCS_SLOW") == "1"
#: Folders of the repository linked into each example's working folder.
LINKED = ("sample_data", "examples")
LANGS = ("console", "python")
REL_TOL = 0.05
#: Outputs shown in the docs were made with the locked libraries; on another set
#: (make test-latest / test-oldest) the commands still run, their digits are not compared.
UNLOCKED = unlocked()

FENCE = re.compile(r"^(?P<fence>`{3,}|~{3,})\s*(?P<info>[^`]*)$")
NUMBER = re.compile(r"[-+−]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?")
EXIT = re.compile(r"#\s*exit\s+(\d+)\s*$")


@dataclass
class Block:
    path: Path
    line: int          # 1-based line of the opening fence
    lang: str
    tags: frozenset[str]
    lines: list[str]

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


@dataclass
class Step:
    argv: list[str]
    exit_code: int
    expected: list[str] = field(default_factory=list)
    line: int = 0


def blocks_of(path: Path) -> list[Block]:
    """Fenced blocks of a Markdown file whose language is console or python."""
    out: list[Block] = []
    lines = path.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i].strip())
        if not m:
            i += 1
            continue
        fence, words = m["fence"], m["info"].split()
        start = i
        body: list[str] = []
        i += 1
        while i < len(lines) and not lines[i].strip().startswith(fence):
            body.append(lines[i])
            i += 1
        i += 1
        if words and words[0] in LANGS:
            out.append(Block(path, start + 1, words[0], frozenset(words[1:]), body))
    return out


def steps_of(block: Block) -> list[Step]:
    """The commands of a console block with their expected exit codes and output."""
    steps: list[Step] = []
    lines = iter(enumerate(block.lines, start=block.line + 1))
    for n, text in lines:
        if text.startswith("$"):
            cmd = text[1:].strip()
            while cmd.endswith("\\"):
                cmd = cmd[:-1] + " " + next(lines)[1].strip()
            m = EXIT.search(cmd)
            code = int(m[1]) if m else 0
            argv = shlex.split(cmd, comments=True)
            assert argv and argv[0] == "armfit", (
                f"{block.where}: line {n}: a console block runs only `$ armfit ...` "
                "commands; use a sh block for other commands")
            assert not {"|", ">", "<", "&&", ";", "2>", ">>"} & set(argv), (
                f"{block.where}: line {n}: no shell syntax in console blocks")
            steps.append(Step(argv[1:], code, line=n))
        elif steps:
            steps[-1].expected.append(text)
        elif text.strip():
            raise AssertionError(f"{block.where}: line {n}: output before any command")
    return steps


# ---------------------------------------------------------------------------
# Comparing shown output with real output
# ---------------------------------------------------------------------------

def _split(line: str) -> tuple[str, list[str]]:
    text = " ".join(line.split())
    return NUMBER.sub("#", text), NUMBER.findall(text)


def _close(shown: str, real: str) -> bool:
    a, b = (float(x.replace("−", "-")) for x in (shown, real))
    digits = shown.split("e")[0].split("E")[0]
    ulp = 10.0 ** -(len(digits.split(".")[1]) if "." in digits else 0)
    if "e" in shown.lower():
        ulp *= 10.0 ** int(re.split("[eE]", shown)[1])
    return abs(a - b) <= max(REL_TOL * abs(a), 2.0 * ulp)


def line_matches(shown: str, real: str) -> bool:
    ts, ns = _split(shown)
    tr, nr = _split(real)
    return ts == tr and len(ns) == len(nr) and all(map(_close, ns, nr))


def check_output(expected: list[str], output: str, where: str) -> None:
    """Every shown line (elisions ``…`` and blank lines aside) matches a real line, in
    order."""
    real = [ln for ln in output.splitlines() if ln.strip()]
    pos = 0
    for shown in expected:
        if not shown.strip() or shown.strip().startswith("…"):
            continue
        for k in range(pos, len(real)):
            if line_matches(shown, real[k]):
                pos = k + 1
                break
        else:
            raise AssertionError(f"{where}: shown line not in the real output (in order):\n"
                                 f"  {shown}\nreal output:\n{output}")


# ---------------------------------------------------------------------------
# Running commands, with a per-session memo of repeated commands
# ---------------------------------------------------------------------------

def _snapshot(root: Path) -> dict[str, tuple[int, int]]:
    out = {}
    for p in root.rglob("*"):
        rel = p.relative_to(root)
        if rel.parts[0] in LINKED or not p.is_file():
            continue
        st = p.stat()
        out[str(rel)] = (st.st_size, st.st_mtime_ns)
    return out


def _digest(path: Path) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


class Runner:
    """Runs armfit commands in a working folder; replays a command already run in the
    session with the same arguments on the same files."""

    def __init__(self, store: Path, memo: dict):
        self.store = store
        self.memo = memo
        self.cli = CliRunner()

    def _key(self, argv: list[str], cwd: Path) -> tuple:
        state = []
        for a in argv:
            p = cwd / a
            if p.is_file():
                state.append((a, _digest(p)))
            elif p.is_dir():  # its files' names, sizes and times
                listing = sorted((str(q.relative_to(p)), q.stat().st_size, q.stat().st_mtime_ns)
                                 for q in p.rglob("*") if q.is_file())
                state.append((a, hashlib.sha1(repr(listing).encode()).hexdigest()))
        return tuple(argv), tuple(state)

    def run(self, argv: list[str], cwd: Path) -> tuple[int, str]:
        key = self._key(argv, cwd)
        if key in self.memo:
            code, output, files = self.memo[key]
            for rel, src in files.items():
                dest = cwd / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(src, dest)
            return code, output
        before = _snapshot(cwd)
        old = Path.cwd()
        os.chdir(cwd)
        try:
            # tables as in a pipe (PIPE_WIDTH): COLUMNS, which a test runner may set, unset
            res = self.cli.invoke(cli, argv, env={"NO_COLOR": "1", "TERM": "dumb",
                                                  "COLUMNS": None})
        finally:
            os.chdir(old)
        after = _snapshot(cwd)
        files = {}
        for rel, stamp in after.items():
            if before.get(rel) != stamp:
                dest = self.store / f"{len(self.memo)}" / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(cwd / rel, dest)
                files[rel] = dest
        if res.exception is not None and not isinstance(res.exception, SystemExit):
            raise res.exception
        self.memo[key] = (res.exit_code, res.output, files)
        return res.exit_code, res.output


@pytest.fixture(scope="session")
def doc_runner(tmp_path_factory) -> Runner:
    """One runner per session: its memo replays repeated commands (e.g. the estimate of
    sample_data) across the documentation files."""
    return Runner(tmp_path_factory.mktemp("docs_memo"), {})


@pytest.mark.parametrize("doc", DOCS, ids=[str(p.relative_to(ROOT)) for p in DOCS])
def test_doc_examples(doc: Path, doc_runner: Runner, tmp_path: Path, monkeypatch) -> None:
    for name in LINKED:
        if (ROOT / name).is_dir():
            (tmp_path / name).symlink_to(ROOT / name, target_is_directory=True)
    namespace: dict = {"__name__": "__docs__"}
    # an example's tempfile.mkdtemp() folder is made in this test's own folder, removed
    # with it (not left in the system's temporary folder at every run of the suite)
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    ran = 0
    for block in blocks_of(doc):
        if "skip" in block.tags or ("slow" in block.tags and not RUN_SLOW):
            continue
        ran += 1
        if block.lang == "python":
            monkeypatch.chdir(tmp_path)
            # leading blank lines: a traceback names the line of the doc
            code = compile("\n" * block.line + "\n".join(block.lines), str(doc), "exec")
            exec(code, namespace)  # noqa: S102 - the documentation's own example
            continue
        for step in steps_of(block):
            where = f"{block.where} (line {step.line}: armfit {' '.join(step.argv)})"
            code, output = doc_runner.run(step.argv, tmp_path)
            assert code == step.exit_code, f"{where}: exit {code}, expected " \
                                           f"{step.exit_code}\n{output}"
            if "check" in block.tags and not UNLOCKED:
                check_output(step.expected, output, where)
    if not ran and doc.name == "README.md":
        pytest.fail("README.md has no runnable example")


# ---------------------------------------------------------------------------
# The harness itself
# ---------------------------------------------------------------------------

def test_number_tolerance() -> None:
    # 5 % or two units of the last shown digit, whichever is larger
    assert line_matches("rms 3.59 dB", "rms  3.60 dB")
    assert line_matches("ΔBIC 3427.8", "ΔBIC 3500.0")
    assert not line_matches("ΔBIC 3427.8", "ΔBIC 3700.0")
    assert line_matches("delay_s=0.012", "delay_s=0.01205")
    assert not line_matches("delay_s=0.012", "delay_s=0.015")
    assert line_matches("x 0.0", "x 0.1")
    assert not line_matches("x 0.0", "x 0.3")
    assert not line_matches("fails 1.12–30 Hz", "fits 1.12–30 Hz")


def test_parse_console_block(tmp_path: Path) -> None:
    md = tmp_path / "x.md"
    md.write_text("text\n```console check\n$ armfit fit-grip s.parquet \\\n"
                  "    -o g.csv   # exit 73\narmfit: error: exists\n```\n"
                  "```sh\n$ ls\n```\n", encoding="utf-8")
    (block,) = blocks_of(md)
    assert block.tags == {"check"} and block.line == 2
    (step,) = steps_of(block)
    assert step.argv == ["fit-grip", "s.parquet", "-o", "g.csv"]
    assert step.exit_code == 73 and step.expected == ["armfit: error: exists"]


# ---------------------------------------------------------------------------
# Links between the documents
# ---------------------------------------------------------------------------

LINK = re.compile(r"\]\(([^)\s]+)\)")
#: A document named in the text rather than linked (``docs/cli.md``).
DOC_NAME = re.compile(r"\bdocs/[\w.-]+\.md\b")


def anchors_of(path: Path) -> set[str]:
    """GitHub's heading anchors of a Markdown file: lower case, punctuation other than
    hyphens removed, spaces as hyphens, a -N suffix for repeats."""
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if FENCE.match(line.strip()):
            fenced = not fenced
        if fenced or not line.startswith("#"):
            continue
        text = line.lstrip("#").strip().replace("`", "").lower()
        slug = re.sub(r"[^\w\- ]", "", text).replace(" ", "-")
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


@pytest.mark.parametrize("doc", DOCS, ids=[str(p.relative_to(ROOT)) for p in DOCS])
def test_doc_links(doc: Path) -> None:
    """Every relative link names an existing file, every #anchor an existing heading, and
    every document named in the text (docs/<name>.md) exists."""
    text = doc.read_text(encoding="utf-8")
    bad = [f"{name}: no such document" for name in DOC_NAME.findall(text)
           if not (ROOT / name).is_file()]
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target):
            continue  # http:, https:, mailto:
        file_part, _, anchor = target.partition("#")
        dest = (doc.parent / file_part).resolve() if file_part else doc
        if not dest.exists():
            bad.append(f"{target}: no such file")
        elif anchor and dest.suffix == ".md" and anchor not in anchors_of(dest):
            bad.append(f"{target}: no such heading")
    assert not bad, f"{doc.relative_to(ROOT)}: broken links: {bad}"


# ---------------------------------------------------------------------------
# docs/cli.md covers the command line as it is
# ---------------------------------------------------------------------------

def _cli_sections() -> dict[str, str]:
    """docs/cli.md's level-2 sections by heading."""
    text = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    parts = re.split(r"^## ", text, flags=re.M)[1:]
    return {p.split("\n", 1)[0].strip(): p for p in parts}


def _subcommands(group):
    """A group's subcommands by name, those loaded on first use included."""
    import click
    ctx = click.Context(group)
    return {n: group.get_command(ctx, n) for n in group.list_commands(ctx)}


def _commands():
    """(name, click command, its section's heading word) for every subcommand; the plot
    subcommands belong to the plot section."""
    import click
    for name, cmd in sorted(_subcommands(cli).items()):
        if isinstance(cmd, click.Group):
            for sub_name, sub in sorted(_subcommands(cmd).items()):
                yield f"{name} {sub_name}", sub, name
        else:
            yield name, cmd, name


def test_cli_md_documents_every_command_and_option() -> None:
    """Each subcommand has a section `## armfit <name>` (possibly shared, e.g. fit-grip and
    fit-nominal) naming each of its options (but -v and -q, which every command takes:
    the conventions name them)."""
    import click
    sections = _cli_sections()
    missing = []
    for full, cmd, name in _commands():
        heads = [h for h in sections if re.search(rf"`?armfit {re.escape(name)}`?(\s|$)", h)]
        if not heads:
            missing.append(f"armfit {name}: no section")
            continue
        body = "".join(sections[h] for h in heads)
        for p in cmd.params:
            if isinstance(p, click.Option) and p.name not in ("help", "verbose", "quiet"):
                opt = max(p.opts, key=len)
                if opt not in body:
                    missing.append(f"armfit {full}: {opt}")
    assert not missing, f"docs/cli.md lacks: {missing}"


def test_cli_md_exit_codes_are_the_code_s() -> None:
    from armfit import errors
    codes = {v for k, v in vars(errors).items() if k.startswith("EXIT_")}
    text = _cli_sections()["Conventions"]
    documented = {int(m) for m in re.findall(r"^\| (\d+) \|", text, flags=re.M)}
    assert documented == codes


def _illustrations(path: Path):
    """(where, argv) of the `armfit ...` lines of a file's sh blocks (not run)."""
    lines = path.read_text(encoding="utf-8").splitlines()
    inside = False
    for n, line in enumerate(lines, start=1):
        m = FENCE.match(line.strip())
        if m:
            inside = not inside and m["info"].split()[:1] == ["sh"]
            continue
        text = line.strip()
        if inside and text.startswith("armfit "):
            k = n
            while text.endswith("\\") and k < len(lines):
                text = text[:-1] + " " + lines[k].strip()
                k += 1
            yield f"{path.relative_to(ROOT)}:{n}", shlex.split(text, comments=True)[1:]


@pytest.mark.parametrize("doc", DOCS, ids=[str(p.relative_to(ROOT)) for p in DOCS])
def test_illustrations_use_real_options(doc: Path) -> None:
    """The `armfit` lines of sh blocks name real subcommands and options (they are not
    run: their paths are a user's)."""
    import click
    bad = []
    for where, argv in _illustrations(doc):
        cmd: click.Command = cli
        def flags(command: click.Command) -> set[str]:   # --x and the --no-x of a switch
            return {o for p in command.params for o in (*getattr(p, "opts", ()),
                                                        *getattr(p, "secondary_opts", ()))}

        known = flags(cli)
        args = [a for a in argv if not a.startswith("-") or a in ("-v", "-q")]
        for a in args:
            subs = _subcommands(cmd) if isinstance(cmd, click.Group) else {}
            if a in subs:
                cmd = subs[a]
                known |= flags(cmd)
        if isinstance(cmd, click.Group):
            bad.append(f"{where}: no subcommand")
            continue
        for a in argv:
            opt = a.split("=", 1)[0]
            if opt.startswith("-") and not NUMBER.fullmatch(opt) and opt not in known:
                bad.append(f"{where}: {cmd.name} has no option {opt}")
    assert not bad, bad

