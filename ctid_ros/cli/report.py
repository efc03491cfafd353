"""Text reports of estimates: the tables and JSON of ``ctid fit`` and ``ctid replay``."""

from ctid_ros.estimation.estimate import Estimate
import numpy as np

__all__ = ['format_table', 'json_default']


def format_table(result: Estimate) -> str:
    """Human-readable table of estimates with standard deviations and 95 % intervals."""
    width = max(len(name) for name in result.params)
    lines = [f'{"parameter":<{max(width, 9)}}  {"estimate":>13}  {"std":>11}  '
             f'{"95% interval":>27}']
    for name, value in result.params.items():
        std = result.std[name]
        lines.append(f'{name:<{max(width, 9)}}  {value:>13.6g}  {std:>11.3g}  '
                     f'[{value - 1.96 * std:>12.6g}, {value + 1.96 * std:>12.6g}]')
    lines.append('')
    lines.append(f'fit {result.fit:.2f} %   iterations {result.iterations}   '
                 f'converged {"yes" if result.converged else "no"} ({result.stop_reason})')
    lines.extend(f'warning: {note}' for note in result.warnings)
    return '\n'.join(lines)


def json_default(value):
    """Convert numpy scalars for :func:`json.dumps` (its ``default`` hook)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f'not JSON serialisable: {type(value).__name__}')
