"""The server's start and stop output as a person reads it (issue 32 item 5): the stop
statistics as a few labelled lines, the ticks since the last reset or load beside the
steps since start, the JSON line only with --stats-json; no 'compiled in' when nothing
compiled."""

from __future__ import annotations

import json
import signal
import sys

from simserver.testing import Client, OutputProcess, ServerProcess, free_port


def test_stop_block_counts_ticks_since_the_reset_and_since_start_and_json_on_request():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    argv = [sys.executable, "-m", "simserver", "serve", "--viewer", "off", "--listen",
            endpoint]
    plain = OutputProcess(argv, ready="ready on")
    try:
        assert plain.wait_ready(180), plain.text()
        client = Client(endpoint)
        try:
            client.wait_state(lambda s: int(s["tick"]) > 500, 20.0, "500 ticks")
            assert client.request("reset")["ok"]
            after = client.wait_state(lambda s: 0 < int(s["tick"]) < 400, 20.0,
                                      "the tick restarted by the reset")
            assert int(after["tick"]) < 400
        finally:
            client.close()
        code = plain.stop(signal.SIGINT, timeout_s=60)
    finally:
        plain.kill()
    text = plain.text()
    assert code == 0, text
    assert "simserver: stopped after " in text and "simserver: stopped {" not in text
    (ticks,) = [ln for ln in text.splitlines() if ln.startswith("  ticks ")]
    since_reset, since_start = (int(part.split(" since")[0].replace(" ", ""))
                                for part in ticks.removeprefix("  ticks").split(", "))
    print(f"\n{ticks.strip()}")
    assert 0 < since_reset < since_start
    for label in ("  timing ", "  commands ", "  states ", "  safety "):
        assert any(ln.startswith(label) for ln in text.splitlines()), label
    assert "compiled in 0.0" not in text  # a start from the cache compiles nothing

    with ServerProcess() as server:  # the harness passes --stats-json
        # stop only after the clock ran: "ready" can come before the first tick
        client = Client(server.endpoint)
        try:
            client.wait_state(lambda s: int(s["tick"]) > 0, 20.0, "the first tick")
        finally:
            client.close()
    final = server.final_stats()
    assert final is not None and final["steps_total"] >= final["ticks"] > 0
    assert "simserver: stopped after " in server.text()
    json.dumps(final)
