"""Records written as ``ctid`` reads them, for the tests of the decision commands."""

import numpy as np


def write_csv(path, data):
    """Write ``data`` as a CSV file with columns t,u,y and return ``path``."""
    times = data.ts * np.arange(len(data))
    np.savetxt(path, np.column_stack([times, data.u, data.y]), delimiter=',', header='t,u,y',
               comments='')
    return path
