"""Tests of bench/generator_eval_tables.py on hand-made rows of generator_eval_bench."""
import sys
import unittest
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import generator_eval_tables as get  # noqa: E402


def row(arm, psnr, lpips, admitted, views, iteration=1000):
    per_view = [dict(view=k, psnr=p, lpips=l, pose_distance=d, **({} if admitted is None else {"admitted": a}))
                for k, (p, l, d, a) in enumerate(views)]
    return dict(scene="fern", views=3, iteration=iteration, arm=arm, psnr=psnr, ssim=0.7, lpips=lpips,
                admitted=admitted, test_views=len(views), per_view=per_view, commit="abc", machine="m")


ROWS = [
    row("render", 20.0, 0.30, None, [(19.0, 0.3, 0.5, None), (21.0, 0.3, 1.5, None)]),
    row("warp", 21.0, 0.25, 1, [(19.5, 0.2, 0.5, True), (22.5, 0.3, 1.5, False)]),
]


class GeneratorEvalTables(unittest.TestCase):
    def test_arm_table_puts_the_render_first_with_differences_to_it(self):
        lines = get.arm_table(list(reversed(ROWS))).splitlines()
        self.assertIn("| fern 3 | 1000 | render | 20.00 | – | 0.700 | 0.300 | – | – |", lines[2])
        self.assertIn("| fern 3 | 1000 | warp | 21.00 | +1.00 | 0.700 | 0.250 | -0.050 | 1/2 |", lines[3])

    def test_distance_table_bins_each_view_against_the_render_at_it(self):
        line = get.distance_table(ROWS).splitlines()[2]
        self.assertEqual(line, "| warp | +0.50 / -0.100 (1, 1) | +1.50 / +0.000 (1, 0) | – |")

    def test_insert_replaces_between_the_markers_only(self):
        doc = "a\n<!-- bench-tables:generator_eval begin -->\nold\n<!-- bench-tables:generator_eval end -->\nb\n"
        out = get.insert(doc, "new\n")
        self.assertEqual(out, doc.replace("old\n", "new\n"))
        with self.assertRaises(SystemExit):
            get.insert("no markers", "x")


if __name__ == "__main__":
    unittest.main()
