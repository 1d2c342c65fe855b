"""The experiments: the paper's Tables II-III (``paper``) and IV (``estimation``), the speed frontier
(``frontier``), the faults of a real flight (``robustness``) and success against the size of a fault
(``fault_curves``), the probes (``speed_probe``, ``margin_probe``), each a fill-in of one skeleton (``skeleton``:
cells -> grid -> summary -> report -> plot), and ``pixelmpc reproduce`` (``reproduce``), which runs them into one
report."""
