"""The one-parse YAML reader reads and refuses exactly what PyYAML's C safe loader does after the checks."""
import math

import numpy as np
import pytest
import yaml

from gls_calibration.calibration.record_file import dump_record
from gls_calibration.common.bounded_yaml import SAFE_LOADER, check_structure, load_bounded_yaml

DEPTH = 32


def _pyyaml(text):
    """What the reader did before: the structure check, then PyYAML's own construction."""
    check_structure(text, DEPTH)
    return yaml.load(text, Loader=SAFE_LOADER)


def _outcome(read, text):
    try:
        return "value", read(text)
    except Exception as error:     # PyYAML lets a few ValueErrors through (a month 13)
        return "error", type(error).__name__, str(error)


def _identical(a, b):
    """Equal values of equal types, floats bit for bit (-0.0 and NaN included), keys in the same order."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return np.float64(a).tobytes() == np.float64(b).tobytes()
    if isinstance(a, list):
        return len(a) == len(b) and all(_identical(x, y) for x, y in zip(a, b))
    if isinstance(a, dict):
        return list(a) == list(b) and all(_identical(a[key], b[key]) for key in a)
    return a == b


CASES = [
    "", "a", "- 1\n- 2", "~",
    # YAML 1.1 numbers a plain float reader would get wrong: octal, hex, underscores, sexagesimal,
    # an exponent without a dot or a sign (strings), capitals, a plus sign, infinities and NaN
    "[1.0, -0.0, 1.0e-05, 1.0e+16, 010, 0x1f, 1_000.5, .inf, -.inf, .nan, 1e5, 1.0e5, 1.0E+5, +1.5, "
    "190:20:30.15, 3, -0, 0o7, 0b101]",
    "[-1.0, -1.5e-300, 1.7976931348623157e+308, 2.0e+400, 4.9e-324, 123456789012345678901234567890.5]",
    "[٣.٥, 1.0]",                                   # non-ASCII digits are no YAML number
    "a: [1.0, '2.0', 3.0]", "a: [1.0, [2.0], 3.0]", "a: [1.0, {b: 2}, 3.0]", "a: [1.0, null, 3.0, true]",
    "- [1.0, 2.0]\n- [3.0, 4.0]\n", "[[1.0, 2.0], 3.0]", "[]", "{}", "a:", "[1.0, ]",
    "[1.0\n\n 2.0, 3.0]", "- 1.0\n\n  2.0\n- 3.0", "[1.0,2.0]", "- 1.0,2.0",   # line breaks and commas in scalars
    "<<: {a: 1}\nb: 2", "a: &x [1]\nb: 2", "a: !!float 1", "a: !!str 1.0", "a: ! 1.0", "!!set {a, b}",
    "a: 1\na: 2", "? [1, 2]\n: x", "{1.5: a, 2: b, null: c, true: d, 2001-12-14: e}", "= : 1", "[=]", "[<<]", "a: <<",
    "t: 2001-12-14t21:59:43.10-05:00", "t: 2002-12-14", "a: 2002-13-45", "x: [yes, no, ~, null, '', true, Off]",
    "a: '1.0'\nb: \"x\\ty\"", "k: |\n  1.0\n", "k: >\n  1.0\n  2.0\n",
    "a: 1\n---\nb: 2", "--- 1\n...\n", "---\n...\n", "# only a comment\n", "%YAML 1.1\n---\na: 1.5\n",
    "x: [1.0, 2.0", "[1.0, 2.0]\n[3.0]", "a: b: c", "a:\n\t- 1", "x: [1.0, *y]", "a: &a [1, 1]\nb: [*a, *a]\n",
    "[" * DEPTH + "]" * DEPTH, "[" * (DEPTH + 1) + "]" * (DEPTH + 1), "{a: " * (DEPTH + 1) + "1" + "}" * (DEPTH + 1),
    "- " * (DEPTH + 1) + "1", "a: [" + "*x, " * 3 + "]", "[[[*x]]] " + "[" * 40, "[" * 40 + "*x",
]


@pytest.mark.parametrize("text", CASES)
def test_the_reader_answers_what_pyyaml_answers(text):
    expected, got = _outcome(_pyyaml, text), _outcome(lambda document: load_bounded_yaml(document, DEPTH), text)
    assert expected[0] == got[0], (expected, got)
    if expected[0] == "value":
        assert _identical(expected[1], got[1]), (expected[1], got[1])
    else:
        assert expected[1:] == got[1:]


def test_a_written_record_of_random_floats_reads_back_bit_for_bit():
    rng = np.random.default_rng(3)
    numbers = np.concatenate([rng.normal(0.0, 100.0, 500), rng.normal(0.0, 1e-3, 500),
                              10.0 ** rng.uniform(-320, 308, 500) * rng.choice([-1.0, 1.0], 500),
                              [0.0, -0.0, 5e-324, 1.7976931348623157e308, 1e16, 1e-5, 123.0]])
    record = {"format_version": 2, "values": numbers.tolist(), "rows": numbers[:600].reshape(-1, 3).tolist(),
              "mixed": [1, 2.5, "three", None, True, [4.0]], "nested": {"a": {"b": [1.0, 2.0]}}}
    text = dump_record(record)
    read = load_bounded_yaml(text, DEPTH)
    assert _identical(read, _pyyaml(text))
    assert np.array_equal(np.array(read["values"]).view(np.uint64), numbers.view(np.uint64))


def test_deep_nesting_is_refused_before_libyaml_composes_it():
    # libyaml's composer recurses once per level: 100 000 levels ended the process (SIGSEGV)
    levels = 100_000
    with pytest.raises(yaml.composer.ComposerError, match=f"nested deeper than {DEPTH} levels"):
        load_bounded_yaml("[" * levels + "]" * levels, DEPTH)


def test_an_alias_bomb_is_refused_at_its_first_alias():
    bomb = "a: &a [x, x]\n" + "".join(f"{chr(98 + i)}: &{chr(98 + i)} [*{chr(97 + i)}, *{chr(97 + i)}]\n"
                                      for i in range(20))
    with pytest.raises(yaml.composer.ComposerError, match="aliases are not allowed") as refused:
        load_bounded_yaml(bomb, DEPTH)
    assert refused.value.problem_mark.line == 1


def test_floats_keep_their_sign_and_nan_stays_nan():
    read = load_bounded_yaml("[-0.0, .nan, -.inf, 0.0]", DEPTH)
    assert math.copysign(1.0, read[0]) == -1.0 and math.isnan(read[1]) and read[2] == -math.inf
    assert math.copysign(1.0, read[3]) == 1.0
