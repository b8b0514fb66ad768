"""The documentation's own checks: a README a person reads, links that resolve, and tables that
are generated from the runs' JSON rather than typed (``scripts/results_tables.py``)."""
import importlib.util
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
DOCS = sorted((REPO / "docs").glob("*.md"))
MAX_README_LINES = 250


def results_tables():
    """``scripts/results_tables.py`` as a module (scripts/ is no package)."""
    spec = importlib.util.spec_from_file_location("results_tables", REPO / "scripts" / "results_tables.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("results_tables", mod)
    spec.loader.exec_module(mod)
    return mod


def without_code(text: str) -> str:
    """``text`` with fenced code blocks dropped and inline code spans replaced by ``code``."""
    text = re.sub(r"^```.*?^```[^\n]*$", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]+`", "code", text)


def test_readme_is_short():
    n = len(README.read_text().splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines (at most {MAX_README_LINES}): move detail to docs/"


def test_setup_block_holds_exactly_the_two_commands_ci_runs():
    """``.ci/run`` reads the install and the test command from between the setup markers (lines
    starting with ``pip`` or ``python``); anything else there would not be run."""
    text = README.read_text()
    block = re.search(r"<!-- setup:begin -->\n(.*?)<!-- setup:end -->", text, flags=re.S)
    assert block, "README.md lost its <!-- setup:begin --> / <!-- setup:end --> markers"
    cmds = [line for line in block.group(1).splitlines() if re.match(r"(pip|python) ", line)]
    assert len(cmds) == 2, cmds
    assert cmds[0].startswith("pip install") and cmds[1].startswith("python -m pytest"), cmds
    body = [line for line in block.group(1).splitlines() if line.strip() and not line.startswith("```")]
    assert body == cmds, "the setup block holds something besides the two commands"


def test_every_generated_block_equals_its_json():
    """Each block between ``<!-- generated:NAME begin/end -->`` markers is what the script renders
    from the committed JSON (``python scripts/results_tables.py`` rewrites them); and every block
    found in the markdown is one the script knows."""
    rt = results_tables()
    for name, block in rt.BLOCKS.items():
        assert (REPO / block.source).is_file(), block.source
        want = rt.render(name, REPO)
        for f in block.files:
            have = rt.read_block((REPO / f).read_text(), name)
            assert have == want, f"{f}: block {name!r} differs from {block.source}: run python scripts/results_tables.py"
    for f in [README] + DOCS:
        unknown = set(rt.generated_blocks(f.read_text())) - set(rt.BLOCKS)
        assert not unknown, f"{f.name}: generated blocks no script renders: {unknown}"
    assert rt.update(REPO, check=True) == []


def test_the_readme_summary_and_the_matrix_come_from_one_json():
    """The README's table is the matrix's run, compact: each checkpoint of the JSON is a row, each
    scored cell's learned AAE appears as the matrix (``tcn_ahrs.experiments.transfer.markdown``) writes it."""
    import json

    from tcn_ahrs.experiments.transfer import markdown

    rt = results_tables()
    result = json.loads((REPO / rt.TRANSFER_JSON).read_text())
    summary, matrix = rt.render("transfer_summary", REPO), rt.render("transfer_matrix", REPO)
    assert matrix.strip() == markdown(result).strip()
    for label, row in result["matrix"].items():
        assert f"| {label} (" in summary and f"| {label} (" in matrix
        for d, c in row.items():
            if isinstance(c, dict) and "learned" in c:
                cell = f"{c['learned']['aae_deg']:.2f} ({c['learned']['inclination_deg']:.2f})"
                assert cell in summary and cell in matrix, (label, d)
                assert ("✓" if c["never_worse"] else "✗") in summary


def _links(md: Path):
    """Relative link and image targets of ``md`` (outside code), without their #anchors."""
    for m in re.finditer(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", without_code(md.read_text())):
        target = m.group(1)
        if re.match(r"[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # http(s):, mailto:, or an anchor in the same page
        yield target.split("#")[0]


@pytest.mark.parametrize("md", [README] + DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(md):
    targets = list(_links(md))
    missing = [t for t in targets if not (md.parent / t).exists()]
    assert not missing, f"{md.relative_to(REPO)}: links to nothing: {missing}"


# A measured decimal: digits, one point, digits, standing alone. Not part of a longer dotted
# number (2.13.0) or of a word/identifier (v1.2, ahrs9d), but a sentence's final point after it
# still counts ("... is 2.23.").
DECIMAL = re.compile(r"(?<![\w.])\d+\.\d+(?!\.?\w)")
# A version number is allowed right after one of these (the install text: "torch (≥ 2.1, ...").
VERSION_BEFORE = re.compile(r"(?:≥|>=|<=|==|~=|\btorch|\bPython|\bversion)\s*$")


def measured_decimals(text: str):
    """The measured decimals of README ``text``, by this rule.

    Numbers measured by a run belong in a generated block (rendered from the run's JSON by
    ``scripts/results_tables.py``) or in docs/results.md, never typed into the README, where they
    would drift from the run. So outside the generated blocks, the README may not hold a decimal
    number (:data:`DECIMAL`: ``2.23``, ``0.69``, ``1.5``), except

    - in fenced code blocks and inline code spans: command arguments and code
      (``data.fold=0``, ``imu[:, 5] = 9.81``) are not measurements;
    - a version number written right after ``≥``/``>=``/``<=``/``==``/``~=``, ``torch``,
      ``Python`` or ``version`` (the install text's "torch (≥ 2.1, ...)");
    - dotted numbers of three or more parts (``2.13.0``), which are versions by form.

    Integers (counts such as "four folds", "50–1000 Hz") are not decimals and are allowed.
    """
    rt = results_tables()
    for name in rt.generated_blocks(text):
        text = text.replace(rt.read_block(text, name), "\n")
    text = without_code(text)
    for m in DECIMAL.finditer(text):
        if VERSION_BEFORE.search(text[max(0, m.start() - 12):m.start()]):
            continue
        yield m.group(0), text[max(0, m.start() - 30):m.end() + 10].replace("\n", " ")


def test_readme_holds_no_typed_measurements():
    found = list(measured_decimals(README.read_text()))
    assert not found, f"README.md types measured numbers outside the generated blocks: {found}"


def test_the_decimal_rule():
    ok = ("torch (≥ 2.1, CPU or CUDA)", "pins torch to 2.13.0.", "`lr=0.003`", "```\nx = 9.81\n```",
          "four folds, 50–1000 Hz", "ahrs9d v1.2")
    bad = ("AAE 2.23 vs 2.48", "inclination 0.69.", "(1.5 h)")
    assert all(not list(measured_decimals(t)) for t in ok)
    assert all(list(measured_decimals(t)) for t in bad)
