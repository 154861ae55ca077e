"""The HTML report is self-contained: tables for nested metrics, images embedded as base64."""
import base64
import json

from planner.html_report import write_html_report


def test_tables_images_and_escape(tmp_path):
    png = tmp_path / "x.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\nfake")
    report = {
        "case": "<case&1>",
        "alignment": {"residual_mm": 0.123456, "iterations": 12},
        "metrics": {
            "overall": {"mean_abs_mm": 0.5, "n_points": 1000},
            "regions": {"chin": {"mean_abs_mm": 1.0, "rms_mm": 1.1},
                        "nose": {"mean_abs_mm": 0.2, "rms_mm": 0.25}},
        },
        "effects": [{"name": "swelling", "rms_after_mm": 0.4}],
    }
    out = write_html_report(tmp_path / "r" / "report.html", "Compare", report, [png],
                            tables={"extra": (["a", "b"], [[1, 2.5]])})
    text = out.read_text()
    assert text.startswith("<!DOCTYPE html>")
    assert "&lt;case&amp;1&gt;" in text and "<case&1>" not in text.split("<pre>")[0]
    assert base64.b64encode(png.read_bytes()).decode() in text
    # the regions become one table with a row per region and a column per metric
    assert text.count("<td class=\"k\">chin</td>") == 1 and "rms_mm</th>" in text
    assert "0.123" in text and "swelling" in text
    # no external references: the page stands alone
    assert "src=\"http" not in text and "href=" not in text
    # the raw JSON is embedded and parses back
    raw = text.split("<pre>")[1].split("</pre>")[0]
    import html
    assert json.loads(html.unescape(raw)) == report
