"""Excitation signals for identification experiments."""

import numpy as np

# Feedback taps of maximal-length linear feedback shift registers (period 2**bits - 1).
_TAPS = {
    3: (3, 2), 4: (4, 3), 5: (5, 3), 6: (6, 5), 7: (7, 6), 8: (8, 6, 5, 4), 9: (9, 5),
    10: (10, 7), 11: (11, 9), 12: (12, 6, 4, 1), 13: (13, 4, 3, 1), 14: (14, 5, 3, 1),
    15: (15, 14), 16: (16, 15, 13, 4),
}


def prbs(bits: int, clock: int = 1, periods: int = 1) -> np.ndarray:
    """
    Maximal-length pseudo-random binary sequence PRBS(bits, clock) with values +-1.

    Parameters
    ----------
    bits : int
        Register length, 3 to 16; one period has ``2**bits - 1`` bits.
    clock : int
        Samples each bit is held (the clock period in samples).
    periods : int
        Number of periods to repeat.

    Returns
    -------
    ndarray
        ``(2**bits - 1) * clock * periods`` samples.

    """
    if bits not in _TAPS:
        raise ValueError(f'bits must be between 3 and 16, got {bits}')
    if clock < 1 or periods < 1:
        raise ValueError('clock and periods must be at least 1')
    register = np.ones(bits, dtype=np.uint8)
    taps = [tap - 1 for tap in _TAPS[bits]]
    sequence = np.empty(2 ** bits - 1)
    for index in range(sequence.size):
        sequence[index] = register[-1]
        feedback = np.bitwise_xor.reduce(register[taps])
        register = np.roll(register, 1)
        register[0] = feedback
    return np.tile(np.repeat(2.0 * sequence - 1.0, clock), periods)
