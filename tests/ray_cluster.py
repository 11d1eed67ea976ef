"""A Ray cluster of two nodes on this machine, for the tests of the Ray backend."""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Iterator

OBJECT_STORE = 80 * 1024 * 1024


@contextlib.contextmanager
def two_node_cluster() -> Iterator:
    """A head node and a second node (ray.cluster_utils.Cluster, one CPU each, small object stores);
    the driver joins it through drsplat.cluster.connect, and leaves and stops it on exit.

    The cluster's nodes are started from this process, which installs Ray's SIGTERM handler here (a
    node's shutdown hook); it is put back when the cluster stops.
    """
    import ray
    from ray.cluster_utils import Cluster

    from drsplat.cluster import connect, disconnect

    node_args = {"num_cpus": 1, "object_store_memory": OBJECT_STORE, "include_dashboard": False}
    sigterm = signal.getsignal(signal.SIGTERM)
    c = Cluster(initialize_head=True, head_node_args=node_args)
    owns = False
    try:
        c.add_node(num_cpus=1, object_store_memory=OBJECT_STORE)
        c.wait_for_nodes()
        owns = connect(c.address)
        assert len([n for n in ray.nodes() if n["Alive"]]) == 2
        yield c
    finally:
        disconnect(owns)
        ray.shutdown()
        c.shutdown()
        signal.signal(signal.SIGTERM, sigterm)
