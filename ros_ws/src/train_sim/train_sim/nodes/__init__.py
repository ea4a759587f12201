"""ROS 2 nodes (thin wrappers around the pure cores).

Imported before any node module: the nodes' callbacks are real-time, so BLAS stays in the
calling thread (``train_core.realtime``, set before numpy loads).
"""

from train_core.realtime import single_threaded_blas

single_threaded_blas()
