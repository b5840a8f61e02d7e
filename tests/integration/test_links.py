"""Direct links (`aero up --links direct`, the default): services started on one host are peers the
router introduces; their samples take the loopback link between them, and a CLI stays a client."""
from __future__ import annotations

import pytest

from aerotest import free_port, poll_until
from aeroperception.schemas import Imu, Vector3
from aeroperception.services.runtime import Node
from aeroperception.services.runtime.session import LINKS_ENV, ZenohConfigError, make_config
from aeroperception.tools.cli.router import open_router


def test_a_service_session_under_direct_links_is_a_loopback_peer_of_the_router(monkeypatch):
    monkeypatch.setenv(LINKS_ENV, "direct")
    conf = make_config(connect="tcp/127.0.0.1:7999", service=True)
    assert conf.get_json("mode") == '"peer"'
    assert conf.get_json("listen/endpoints") == '["tcp/127.0.0.1:0"]'
    assert conf.get_json("connect/endpoints") == '["tcp/127.0.0.1:7999"]'
    # A CLI, or a session whose mode is asked for, is left alone
    assert make_config(connect="tcp/127.0.0.1:7999").get_json("mode") == '"client"'
    assert make_config(mode="router", service=True).get_json("mode") == '"router"'
    monkeypatch.setenv(LINKS_ENV, "router")
    assert make_config(service=True).get_json("mode") == '"client"'
    monkeypatch.setenv(LINKS_ENV, "p2p")
    with pytest.raises(ZenohConfigError, match=r"\$AERO_LINKS='p2p': expected one of router, direct"):
        make_config(service=True)


@pytest.mark.timeout(60)
def test_direct_peers_keep_talking_while_their_router_is_down(monkeypatch):
    """The proof the samples take the direct link: with the router gone they still arrive."""
    monkeypatch.setenv(LINKS_ENV, "direct")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(None, [endpoint])
    nodes = [Node(n, connect=endpoint) for n in ("talker", "listener")]
    got: list[float] = []
    try:
        for n in nodes:
            assert n.connect(max_wait_s=5.0)
        talker, listener = nodes
        listener.subscribe("test/links", Imu, lambda m: got.append(m.linear_acceleration_mps2.x))
        pub = talker.publisher("test/links", Imu)
        send = lambda x: pub.publish(Imu(linear_acceleration_mps2=Vector3(x=x))) or x in got  # noqa: E731
        assert poll_until(lambda: send(1.0), 10, 0.05), "no sample in 10 s"
        # The router introduces the peers (gossip) and they link
        peer = str(listener.session.info.zid())
        assert poll_until(lambda: peer in [str(z) for z in talker.session.info.peers_zid()], 10, 0.05), \
            "the router never introduced the peers"
        router.close()
        router = None
        assert poll_until(lambda: send(2.0), 10, 0.05), "no sample between the peers in 10 s with the router down"
    finally:
        for n in nodes:
            n.close()
        if router is not None:
            router.close()
