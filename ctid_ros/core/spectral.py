"""
The frequency response seen in the data alone, to hold a model's Bode plot against.

:func:`spectral_response` is the nonparametric estimate MATLAB's ``spa``/``etfe`` users look
at next to a parametric model: Welch's averaged periodograms of the input and the output (Hann
windows, half overlapping, means removed) and the H1 estimate ``G = S_yu / S_uu`` with the
coherence ``|S_yu|² / (S_uu S_yy)`` that says where it can be believed (near 1: the output at
that frequency is explained by the input; near 0: noise, or no excitation there). Frequencies
run from the first bin above zero to the last below the Nyquist frequency (both are real bins,
without a phase). The phase is unwrapped continuously from the lowest frequency along the
coherent frequencies, so a dead time shows as a steadily falling line.

Under feedback (the input computed from the noisy output) the H1 estimate is biased where the
noise dominates the excitation: compare with the model where the coherence is high.
"""

from dataclasses import dataclass
from typing import Optional

import numpy as np

__all__ = ['SpectralResponse', 'spectral_response']

# Fewest samples per segment, and the record over the segment length (a quarter of the record:
# seven half-overlapping segments; longer segments resolve lower frequencies, more of them give
# a smoother estimate).
MIN_SEGMENT = 64
SEGMENTS = 4


@dataclass(frozen=True)
class SpectralResponse:
    """
    A frequency response estimated from input and output samples.

    Attributes
    ----------
    omega : ndarray
        Angular frequencies in rad/s, increasing, above zero and below the Nyquist frequency.
    response : ndarray
        Complex response ``S_yu / S_uu`` at ``omega``.
    coherence : ndarray
        Squared coherence in ``[0, 1]`` at ``omega``.
    segment : int
        Samples per Welch segment (the resolution is ``2 pi / (segment ts)`` rad/s).

    """

    omega: np.ndarray
    response: np.ndarray
    coherence: np.ndarray
    segment: int

    @property
    def magnitude_db(self) -> np.ndarray:
        """Return the magnitude in dB."""
        return 20.0 * np.log10(np.abs(self.response))

    def phase_deg(self, start: Optional[float] = None, coherent: float = 0.5) -> np.ndarray:
        """
        Return the phase in degrees, unwrapped from the lowest frequency upwards.

        The phase is unwrapped along the frequencies whose coherence is at least ``coherent``
        (noise elsewhere would add or lose whole turns); every other frequency is put within
        half a turn of the phase interpolated between them. ``start`` (degrees) chooses the
        branch: the phase at the lowest frequency is moved by whole turns to lie within half a
        turn of it (e.g. a model's phase there).
        """
        angle = np.angle(self.response)
        trusted = self.coherence >= coherent
        if np.count_nonzero(trusted) < 2:
            trusted = np.ones_like(trusted)
        phase = np.empty_like(angle)
        phase[trusted] = np.unwrap(angle[trusted])
        between = np.interp(self.omega[~trusted], self.omega[trusted], phase[trusted])
        phase[~trusted] = between + np.angle(np.exp(1j * (angle[~trusted] - between)))
        phase = np.degrees(phase)
        if start is not None and phase.size:
            phase = phase - 360.0 * np.round((phase[0] - start) / 360.0)
        return phase


def spectral_response(u, y, ts: float, segment: Optional[int] = None) -> SpectralResponse:
    """
    Estimate the frequency response from ``u`` to ``y`` by Welch's method (H1).

    Parameters
    ----------
    u, y : array_like
        Input and output, one sample per ``ts``, the same length (one input).
    ts : float
        Sample time in seconds.
    segment : int, optional
        Samples per segment; default about a quarter of the record, a power of two, at least
        64 (and at most the record).

    Returns
    -------
    SpectralResponse
        Frequencies where the input has power (bins with none are left out).

    Raises
    ------
    ValueError
        If the signals differ in length, have fewer than 16 samples, or ``ts`` is not positive.

    """
    u = np.asarray(u, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    if u.size != y.size or u.size < 16:
        raise ValueError(f'need input and output of the same length, at least 16 samples; got '
                         f'{u.size} and {y.size}')
    if not ts > 0:
        raise ValueError(f'the sample time must be positive, got {ts}')
    if segment is None:
        segment = max(MIN_SEGMENT, 2 ** int(np.floor(np.log2(max(u.size // SEGMENTS, 1)))))
    segment = int(min(segment, u.size))
    # Imported here: scipy.signal brings scipy.stats, which nothing else of an estimate needs.
    from scipy import signal
    options = {'fs': 1.0 / ts, 'window': 'hann', 'nperseg': segment, 'detrend': 'constant'}
    frequency, s_uu = signal.welch(u, **options)
    _, s_yy = signal.welch(y, **options)
    _, s_uy = signal.csd(u, y, **options)
    # The bins at zero and at the Nyquist frequency are real: no phase there.
    keep = (frequency > 0) & (frequency < 0.5 / ts) & (s_uu > 1e-12 * np.max(s_uu))
    s_uu, s_yy, s_uy = s_uu[keep], s_yy[keep], s_uy[keep]
    coherence = np.abs(s_uy) ** 2 / np.maximum(s_uu * s_yy, np.finfo(float).tiny)
    return SpectralResponse(2.0 * np.pi * frequency[keep], s_uy / s_uu,
                            np.clip(coherence, 0.0, 1.0), segment)
