"""service: the REST layer, storage and durable job queue around calib_core (calib_core never imports this)."""
import os

# One job per worker process: small dense linear algebra runs fastest on one BLAS thread, and several
# processes on a multi-threaded BLAS oversubscribe the cores (measured 3-7x slower on 2 cores).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
