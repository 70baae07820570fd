"""The viewer writes measured numbers as the report and the command line do: plot.js's
formatMeasured against fractoscope.numbers.with_uncertainty, run in Node."""

import json
import subprocess
from pathlib import Path

from fractoscope.numbers import with_uncertainty

ROOT = Path(__file__).resolve().parents[3]
CASES = [
    (16.115, 1.62, "µm"),
    (31.2234, 0.00089, "%"),
    (5.0, 0.0996, "µm"),
    (1234.5, 150.0, "µm"),
    (-0.0001, 0.02, "µm"),
    (0.7634, 0.1441, "1"),
    (72.12, 18.4, "%"),
    (2.5, None, "µm"),
]


def test_the_viewer_and_the_report_write_a_number_alike():
    script = (
        "import { formatMeasured } from './clients/web/plot.js';"
        f"const cases = {json.dumps(CASES)};"
        "console.log(JSON.stringify(cases.map(([v, u, unit]) => formatMeasured(v, u, unit))));"
    )
    done = subprocess.run(
        ["node", "--input-type=module", "-e", script], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == [with_uncertainty(*case) for case in CASES]
