"""The table of README.md from this folder's JSON files (and the default's)."""
import json
from pathlib import Path

HERE = Path(__file__).parent


def row(name, piles, paper=None, train=None):
    p = json.loads((HERE / piles).read_text())
    r = p["ranking"]
    cells = [name, f"{1000 * p['test_l1_m']:.1f}", f"{r['spearman_mean']:.3f}",
             f"{r['spearman_median']:.3f}", f"{1000 * r['regret_median_m']:.1f}",
             f"{100 * r['top1_within_1cm']:.1f}%"]
    if paper:
        q = json.loads((HERE / paper).read_text())
        cells += [f"{1000 * q['test_l1_m']:.2f}", f"{q['ranking']['spearman_mean']:.3f}"]
    else:
        cells += ["", ""]
    cells.append(f"{1000 * train:.1f}" if train is not None else "")
    return "| " + " | ".join(cells) + " |"


def main() -> None:
    print("| 100 held-out piles, 1,000 ranking images | L1 mm | Spearman mean | median | "
          "regret median mm | top-1 within 1 cm | paper test: L1 mm | Spearman mean | "
          "train L1 mm (own mix) |")
    print("|---|---|---|---|---|---|---|---|---|")
    print(row("the default", "default_on_clutter_test_r1000.json"))
    for arm in ("mirror", "d4"):
        m = json.loads((HERE / f"train_metrics_{arm}.json").read_text())
        for e in (1, 2, 3):
            train = m["epochs"][e - 1]["train_l1_m"]
            paper = f"{arm}_epoch3_on_paper_test.json" if e == 3 else None
            print(row(f"{arm}, epoch {e}", f"{arm}_epoch{e}_on_clutter_test_r1000.json",
                      paper, train))


if __name__ == "__main__":
    main()
