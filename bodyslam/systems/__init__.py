"""The field's other localization systems on the same testbed: Ito's UWB TOA / MICS RSSI particle filters
(papers 002/003, ``pf``), Jeong's TOA/DOA + IMU EKF with its PCRB (paper 000, ``toa_doa``), Popek's magnetic
capsule EKF (paper 001, ``magnetic``)."""
