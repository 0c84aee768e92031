"""Benchmark: build time of the default anatomy's model (docs/method.md section 1; target < 5 s).

Builds the bundled lower limb with default ("paper") settings (or, while the bundled anatomy is
absent, the synthetic 'limb' phantom of tests/phantoms.py), prints the build time (first build in
this process, including imports, and the median of the following runs), the Table-1 rows side by
side with the paper and their ratios, and the build time of the limb built R times finer (--refine, one build each:
wall and CPU seconds, vertices, cells). Last line: one JSON object.

    .venv/bin/python bench/build.py [--runs 3] [--refine 3[,6]]
"""
from __future__ import annotations

import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / 'src' / 'tissue_sim'))
sys.path.insert(0, str(ROOT / 'tests'))


def main():
    from tissue_sim.errors import ArgumentParser, bounded
    ap = ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--runs', type=bounded(int, low=1), default=3)
    ap.add_argument('--refine', default='3', help="refinements R to time, e.g. 3,6 ('none': skip)")
    args = ap.parse_args()
    try:
        refine = [] if args.refine == 'none' else [int(r) for r in args.refine.split(',')]
    except ValueError:
        ap.error(f'--refine: not a comma-separated list of integers: {args.refine!r}')
    t_import = time.perf_counter()
    from tissue_sim.core import builder
    import_s = time.perf_counter() - t_import
    try:
        labels, tissues = builder.default_inputs()
        src, inputs = 'bundled anatomy', (str(labels), str(tissues))
    except FileNotFoundError:
        from phantoms import make_limb_phantom
        lab, aff, tab = make_limb_phantom()
        src, inputs = 'synthetic limb phantom (bundled anatomy absent)', ((lab, aff), tab)
    times = []
    for i in range(1 + args.runs):
        t0 = time.perf_counter()
        tm, rep = builder.build_model(*inputs)
        times.append(time.perf_counter() - t0 + (0.0 if i else import_s))
    first, med = times[0], statistics.median(times[1:])
    t1 = rep['table1']
    print(f'input: {src}')
    print(f'build time: first {first:.2f} s (cold: with imports of the builder and its libraries), median of {args.runs} more {med:.2f} s; target < 5 s')
    print(f'{"Table 1 row":<18}{"model":>8}{"paper":>8}{"ratio":>8}')
    ratios = {}
    for k, lab in builder.TABLE1_LABELS.items():
        p = builder.PAPER_TABLE1[k]
        ratios[k] = round(t1[k] / p, 3)
        print(f'{k:<18}{t1[k]:>8}{p:>8}{ratios[k]:>8.2f}')
    print(f'fat vertices (distinct) {t1["fat_vertices_unique"]}; inverted cells {rep["cells"]["inverted"]}; '
          f'closed surfaces {rep["closed_surfaces"]}; median polygon/label area {rep["areas"]["median_ratio"]}')
    q = rep['quality']
    vr = q['volume_ratio']
    worst = max(vr, key=lambda k: abs(vr[k] - 1))
    print(f'built / label volume: fat {vr.get("fat")}, muscles {min(v for k, v in vr.items() if k != "fat"):.3f}..'
          f'{max(v for k, v in vr.items() if k != "fat"):.3f} (worst {worst} {vr[worst]}); chain breaks {len(q["breaks"])}')
    for tname, sh in q['shear'].items():
        print(f'{tname} cells: shear (ring distortion / height) median {sh["median"]}, p95 {sh["p95"]}, max {sh["max"]}, '
              f'{sh["over_limit"]} of {sh["cells"]} over {q["shear_limit"]:g}; slant median {sh["slant_median"]}, '
              f'p95 {sh["slant_p95"]}, max {sh["slant_max"]}')
    for w in q['warnings']:
        print(f'quality warning: {w}')
    finer = []
    if refine and src == 'bundled anatomy':
        print(f'{"R":>3}{"vertices":>10}{"cells":>8}{"wall s":>9}{"CPU s":>8}')
        for r in refine:
            t0, c0 = time.perf_counter(), time.process_time()
            fm, _ = builder.build_model(*inputs, refine=r)
            finer.append({'refine': r, 'vertices': int(len(fm.rest_positions)), 'cells': int(fm.n_cells),
                          'wall_s': round(time.perf_counter() - t0, 2), 'cpu_s': round(time.process_time() - c0, 2)})
            f = finer[-1]
            print(f'{r:>3}{f["vertices"]:>10,}{f["cells"]:>8,}{f["wall_s"]:>9.1f}{f["cpu_s"]:>8.1f}')
    within = all(abs(r - 1) <= 0.25 for k, r in ratios.items() if k not in ('bones', 'muscles'))
    print(json.dumps({'bench': 'build', 'input': src, 'build_s_first': round(first, 3), 'build_s_median': round(med, 3),
                      'target_s': 5.0, 'under_target': first < 5.0 and med < 5.0, 'table1': t1,
                      'paper_table1': builder.PAPER_TABLE1, 'ratio_to_paper': ratios, 'within_25pct': within,
                      'inverted_cells': rep['cells']['inverted'], 'closed_surfaces': rep['closed_surfaces'],
                      'volume_ratio': vr, 'shear': q['shear'], 'chain_breaks': len(q['breaks']),
                      'quality_warnings': q['warnings'], 'finer': finer}))


if __name__ == '__main__':
    main()
