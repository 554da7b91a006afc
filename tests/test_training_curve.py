"""``bench/training_curve.py``: recorded yardstick rows drawn against training steps."""

from pathlib import Path

import pytest
from PIL import Image

from iwsim.core.errors import InputError
from tests.tools.scripts import load_script

ROOT = Path(__file__).resolve().parents[1]
HEADER = "arm,steps,t_kept_192,t_kept_2000,expert_takes,machine\n"


def test_rows_are_drawn_per_arm_and_machine(tmp_path):
    curve = load_script(ROOT / "bench" / "training_curve.py")
    rows = tmp_path / "rows.csv"
    rows.write_text(HEADER + "a,3000,30,1,31,one\na,6500,37.3,,,one\na,4500,32,1,31,two\nb,21400,77,90,30,one\n")
    read = curve.read_rows(rows)
    assert [r["steps"] for r in read] == ["3000", "6500", "4500", "21400"] and read[1]["expert_takes"] == ""
    out = tmp_path / "curve.png"
    curve.plot(read, out)
    with Image.open(out) as im:
        assert im.width > 3 * im.height / 2 and len(im.convert("L").getcolors(65536)) > 10
    assert not list(tmp_path.glob(".curve*"))  # written atomically, no temporary file left


@pytest.mark.parametrize("text, message", [
    ("arm,steps,machine\na,1,x\n", "lacks the column"),
    (HEADER + "a,3k,30,1,31,one\n", "line 2: steps '3k'"),
    (HEADER + "a,1,30,1,31,one\na,2,n/a,1,31,one\n", "line 3: t_kept_192 'n/a'"),
])
def test_bad_rows_are_named(tmp_path, text, message):
    curve = load_script(ROOT / "bench" / "training_curve.py")
    rows = tmp_path / "rows.csv"
    rows.write_text(text)
    with pytest.raises(InputError, match=message):
        curve.read_rows(rows)
