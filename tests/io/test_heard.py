"""A data stream nobody hears is not made (service/io/bus/heard.py): the bus follows each publisher's matching
status, makes and sends only what some subscriber matches, and counts the rest in unheard_<stream>; a subscriber
that comes later hears every message from the moment the bus knows of it, and one that leaves stops the sending."""

from __future__ import annotations

from contextlib import ExitStack

import numpy as np
from test_zenoh_bus import collect, make_block, make_corrected, peer_cfg, wait_until

from fluxcal.service.io.bus import BusClient, ServiceBus, ZenohConfig

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.io.bus.heard",)


def test_what_no_subscriber_matches_is_not_made_and_is_counted():
    cfg, ep = peer_cfg()
    with ExitStack() as stack:
        bus = stack.enter_context(ServiceBus(cfg, "grad1", probe_names=["s1", "s2", "s3", "s4"]))
        assert not any(bus.has_subscribers(s) for s in ("raw", "corrected", "diff", "tensor", "error", "corrected/s2"))
        block = make_block(20, 4, seq0=100)
        for _ in range(3):                                # nobody listens: nothing made, every message counted
            bus.publish_raw(block)
            bus.publish_corrected(make_corrected(block))
            bus.publish_error({"s1.scalar": 0.5}, seq=100, t_s=0.0, n=20)
        assert bus.flush(5.0)
        st = bus.stats
        assert [st[f"published_{s}"] for s in ("raw", "corrected", "diff", "tensor", "error")] == [0] * 5
        assert st["published_corrected_probe"] == 0
        assert [st[f"unheard_{s}"] for s in ("raw", "corrected", "diff", "tensor", "error")] == [3] * 5
        assert st["unheard_corrected_probe"] == 3 * 4

        client = stack.enter_context(BusClient(ZenohConfig.client(ep), "grad1", streams=["corrected", "corrected/s2"]))
        wait_until(lambda: bus.has_subscribers("corrected") and bus.has_subscribers("corrected/s2"),
                   what="the subscriber known to the bus")
        later = make_block(20, 4, seq0=200, seed=1)
        cor = make_corrected(later)
        bus.publish_raw(later)
        bus.publish_corrected(cor)
        got = {m.stream: m.value for m in collect(client, 2)}
        # the streams heard arrive whole; the others (raw, diff, tensor, the three other probes) are still not made
        np.testing.assert_array_equal(got["corrected"].corrected_nT, cor.corrected_nT)
        np.testing.assert_array_equal(got["corrected/s2"].corrected_nT[:, 0], cor.corrected_nT[:, 1])
        assert st["published_corrected"] == 1 and st["published_corrected_probe"] == 1
        assert st["unheard_raw"] == 4 and st["unheard_diff"] == 4 and st["unheard_corrected_probe"] == 3 * 4 + 3

        client.close()                                    # the subscriber leaves: the bus stops making its stream
        wait_until(lambda: not bus.has_subscribers("corrected"), what="the bus to see the subscriber gone")
        bus.publish_corrected(cor)
        assert st["published_corrected"] == 1 and st["unheard_corrected"] == 4
