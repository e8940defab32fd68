"""The field's other localization systems on the same testbed: Ito's UWB TOA / MICS RSSI particle filters
(papers 002/003, ``pf``), Jeong's TOA/DOA + IMU EKF with its PCRB (paper 000, ``toa_doa``), Popek's magnetic
capsule EKF (paper 001, ``magnetic``)."""


def runs_of(ks) -> list[tuple[int, int]]:
    """Runs of consecutive integers in sorted ``ks``, as ``(first, last)``: the slots a recording lacks, listed once
    per run (:mod:`~bodyslam.systems.magnetic`, :mod:`~bodyslam.systems.toa_doa`)."""
    out: list[tuple[int, int]] = []
    for k in ks:
        k = int(k)
        if out and k == out[-1][1] + 1:
            out[-1] = (out[-1][0], k)
        else:
            out.append((k, k))
    return out
