"""Running tacfoot's MicroPython code off the board: the WebAssembly port under
Node (:mod:`device.sim.mpy.runner`, ``run.mjs``) and a ``machine`` stand-in
(``lib/machine.py``) for it and for CPython."""
