"""
The fleet report of ``ctid fleet``: one row per robot, outliers flagged, one figure per parameter.

Per robot and parameter, the estimates of its rows (its bags, or with ``--span`` the spans of
its bags) are combined with inverse-variance weights; the combined standard deviation is widened
by the Birge ratio (``sqrt(chi2 / (n - 1))`` when above 1) where the rows scatter more than their
own standard deviations allow (the plant varies from day to day or within a bag, or the model is
not exact). Spans are pooled exactly as bags are: they are disjoint stretches of data with
independent noise, so for a steady plant their inverse-variance mean is close to the estimate
over the whole bag (and its std to that estimate's), and a plant that changes within a bag
widens the std through the Birge ratio instead of being averaged away silently.

A robot is **flagged** for a parameter when its robust z-score

    z = (value - fleet median) / sqrt(std**2 + (1.4826 * MAD)**2)

exceeds :data:`Z_LIMIT` in magnitude: the distance from the median of the robots, in units of
the robot's own uncertainty combined with the fleet's robust spread (the median absolute
deviation of the robots' values, which one outlier cannot inflate). ``flag_reason`` says which
parameters, by how much and at which z.
"""

import math
from pathlib import Path
from typing import Any, Dict, List, Sequence

import numpy as np

__all__ = ['MAD_SCALE', 'Z_LIMIT', 'combine', 'flag_robots', 'write_figures',
           'write_robot_tables']

# Robust z-score beyond which a robot is flagged (Iglewicz and Hoaglin's 3.5).
Z_LIMIT = 3.5
# The median absolute deviation of normal data times this is their standard deviation.
MAD_SCALE = 1.4826


def combine(values: Sequence[float], stds: Sequence[float]) -> tuple:
    """
    Combine estimates of one quantity: inverse-variance mean and its standard deviation.

    The standard deviation is widened by the Birge ratio when the estimates scatter more than
    their standard deviations allow; estimates without a positive finite std are averaged
    plainly (std of the mean of their spread).

    Returns
    -------
    (float, float)
        The combined value and standard deviation (NaN, NaN without any finite value).

    """
    x = np.asarray(values, dtype=float)
    s = np.asarray(stds, dtype=float)
    finite = np.isfinite(x)
    x, s = x[finite], s[finite]
    if x.size == 0:
        return math.nan, math.nan
    if not np.all(np.isfinite(s) & (s > 0)):
        spread = float(np.std(x, ddof=1)) / math.sqrt(x.size) if x.size > 1 else math.nan
        return float(np.mean(x)), spread
    weights = 1.0 / s ** 2
    mean = float(np.sum(weights * x) / np.sum(weights))
    std = 1.0 / math.sqrt(float(np.sum(weights)))
    if x.size > 1:
        birge = float(np.sum(weights * (x - mean) ** 2)) / (x.size - 1)
        std *= math.sqrt(max(1.0, birge))
    return mean, std


def flag_robots(bags: List[Dict[str, Any]], names: Sequence[str]) -> List[Dict[str, Any]]:
    """
    Return one row per robot: combined parameters, std, z-scores and the flag.

    Parameters
    ----------
    bags : list of dict
        Rows of ``bags.parquet`` (``robot``, ``bag``, ``status``, ``start`` and a value and
        ``_std`` per parameter), one per bag or per span.
    names : sequence of str
        The parameters.

    Returns
    -------
    list of dict
        Keys ``robot``, ``bags`` (with at least one estimate), ``errors`` (error rows),
        ``estimates`` (the rows pooled: bags, or spans), ``first``, ``last`` (ns), per
        parameter ``<name>``, ``<name>_std`` and ``<name>_z``, then ``flagged`` and
        ``flag_reason``.

    """
    robots: Dict[str, Dict[str, Any]] = {}
    for row in bags:
        robot = robots.setdefault(str(row['robot']), {'ok': [], 'errors': 0})
        if row['status'] == 'ok':
            robot['ok'].append(row)
        else:
            robot['errors'] += 1
    table = []
    for robot, found in sorted(robots.items()):
        starts = [row['start'] for row in found['ok'] if row.get('start') is not None]
        entry: Dict[str, Any] = {'robot': robot,
                                 'bags': len({row.get('bag') for row in found['ok']}),
                                 'errors': found['errors'], 'estimates': len(found['ok']),
                                 'first': min(starts) if starts else None,
                                 'last': max(starts) if starts else None}
        for name in names:
            entry[name], entry[f'{name}_std'] = combine(
                [row.get(name, math.nan) for row in found['ok']],
                [row.get(f'{name}_std', math.nan) for row in found['ok']])
        table.append(entry)
    reasons: Dict[str, List[str]] = {entry['robot']: [] for entry in table}
    for name in names:
        values = np.array([entry[name] for entry in table], dtype=float)
        known = np.isfinite(values)
        median = float(np.median(values[known])) if np.any(known) else math.nan
        spread = MAD_SCALE * float(np.median(np.abs(values[known] - median))) \
            if np.any(known) else math.nan
        for entry, value in zip(table, values):
            std = entry[f'{name}_std']
            scale = math.sqrt((std if math.isfinite(std) else 0.0) ** 2 + spread ** 2)
            z = (value - median) / scale if scale > 0 and math.isfinite(value) else math.nan
            entry[f'{name}_z'] = z
            if math.isfinite(z) and abs(z) > Z_LIMIT:
                change = f'{100 * (value / median - 1):+.1f} %, ' if median else ''
                reasons[entry['robot']].append(
                    f'{name} {value:.6g} ± {std:.2g} against the fleet median {median:.6g} '
                    f'({change}z = {z:+.1f})')
    for entry in table:
        entry['flagged'] = bool(reasons[entry['robot']])
        entry['flag_reason'] = '; '.join(reasons[entry['robot']])
    return table


def write_robot_tables(results: Path, robots: List[Dict[str, Any]], names: Sequence[str]
                       ) -> None:
    """Write ``robots.parquet`` and ``robots.csv``."""
    import pyarrow as pa
    import pyarrow.csv as pa_csv
    import pyarrow.parquet as pq

    columns = ['robot', 'bags', 'errors', 'estimates', 'first', 'last']
    for name in names:
        columns += [name, f'{name}_std', f'{name}_z']
    columns += ['flagged', 'flag_reason']
    data = {}
    for column in columns:
        values = [row[column] for row in robots]
        if column in ('first', 'last'):
            data[column] = pa.array(values, type=pa.int64()).cast(pa.timestamp('ns', tz='UTC'))
        elif column in ('robot', 'flag_reason'):
            data[column] = pa.array(values, type=pa.string())
        elif column in ('bags', 'errors', 'estimates'):
            data[column] = pa.array(values, type=pa.int64())
        elif column == 'flagged':
            data[column] = pa.array(values, type=pa.bool_())
        else:
            data[column] = pa.array(values, type=pa.float64())
    table = pa.table(data)
    pq.write_table(table, results / 'robots.parquet')
    pa_csv.write_csv(table, results / 'robots.csv')


def write_figures(results: Path, bags: List[Dict[str, Any]], robots: List[Dict[str, Any]],
                  names: Sequence[str]) -> List[Path]:
    """
    Write ``fleet_<name>.png`` per parameter: the fleet's distribution and each robot's trend.

    Left, each robot's combined value with ±2σ and the fleet median with the band within which
    a robot is not flagged for a robot of zero std; right, every bag's (or span's) estimate
    (±2σ) at the middle of the data it was estimated on, one line per robot, so spans trace the
    parameter through a bag. Flagged robots are drawn in red.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.dates as mdates
    import matplotlib.pyplot as plt

    written = []
    flagged = {row['robot'] for row in robots if row['flagged']}
    for name in names:
        figure, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5),
                                             gridspec_kw={'width_ratios': [1, 2]})
        values = np.array([row[name] for row in robots], dtype=float)
        stds = np.array([row[f'{name}_std'] for row in robots], dtype=float)
        known = np.isfinite(values)
        if np.any(known):
            median = float(np.median(values[known]))
            spread = MAD_SCALE * float(np.median(np.abs(values[known] - median)))
            left.axhline(median, color='0.3', lw=1, label='fleet median')
            left.axhspan(median - Z_LIMIT * spread, median + Z_LIMIT * spread, color='0.9',
                         label=f'|z| ≤ {Z_LIMIT:g} (std 0)')
        for index, row in enumerate(robots):
            colour = 'tab:red' if row['robot'] in flagged else 'tab:blue'
            left.errorbar(index, values[index], yerr=2 * np.nan_to_num(stds[index]), fmt='o',
                          color=colour, capsize=3)
        left.set_xticks(range(len(robots)), [row['robot'] for row in robots], rotation=45,
                        ha='right')
        left.set_ylabel(name)
        left.set_title(f'{name} per robot (±2σ)')
        left.legend(fontsize=8)
        palette = [colour for colour in plt.rcParams['axes.prop_cycle'].by_key()['color']
                   if colour not in ('#d62728',)]
        for number, robot in enumerate(sorted({str(row['robot']) for row in bags})):
            own = sorted((row for row in bags if str(row['robot']) == robot and
                          row['status'] == 'ok' and row.get('start') is not None),
                         key=lambda row: row['start'])
            if not own:
                continue
            times = [np.datetime64((int(row['start']) + int(row.get('end') or row['start'])) // 2,
                                   'ns') for row in own]
            colour = 'tab:red' if robot in flagged else palette[number % len(palette)]
            right.errorbar(times, [row[name] for row in own],
                           yerr=[2 * (row.get(f'{name}_std') or 0.0) for row in own],
                           marker='o', ms=3, capsize=2, color=colour,
                           label=f'{robot} (flagged)' if robot in flagged else robot)
        right.xaxis.set_major_formatter(mdates.ConciseDateFormatter(
            mdates.AutoDateLocator()))
        spans = any(row.get('span') is not None for row in bags)
        right.set_title(f'{name} per {"span" if spans else "bag"} over time (±2σ)')
        right.legend(fontsize=8, ncol=2)
        figure.tight_layout()
        path = results / f'fleet_{name}.png'
        figure.savefig(path, dpi=100)
        plt.close(figure)
        written.append(path)
    return written
