"""A ground client of a running ``fprime-gds``, for the tests: fprime-gds's own Python API
(its standard pipeline and ``IntegrationTestAPI``) on the GDS's ZMQ transport.  Prints one JSON
object per channel value fprime-gds decoded — ``{"name", "id", "t", "value"}`` (``value``: the
enum's name for an enum) — and per event — ``{"event", "id", "args"}`` — until it is killed or
``SECONDS`` pass.  With ``COMMAND`` (a command's full name), it sends that command through
fprime-gds once the first channel value has arrived (the flight side is then connected).

    python tests/fprime_peer.py DICTIONARY ZMQ_IN ZMQ_OUT SECONDS LOG_DIRECTORY [COMMAND]

It runs in a process of its own: fprime-gds keeps process-wide singletons (its configuration
manager) that must not leak into the test process.
"""

from __future__ import annotations

import json
import sys
import time


def main(argv: list[str]) -> int:
    from fprime_gds.common.testing_fw.api import IntegrationTestAPI
    from fprime_gds.executables.cli import ParserBase, StandardPipelineParser

    dictionary, zmq_in, zmq_out, seconds, logs, *command = argv
    args, *_ = ParserBase.parse_known_args(
        [StandardPipelineParser], "aurora-gateway test peer",
        arguments=["--dictionary", dictionary, "--zmq-transport", zmq_in, zmq_out,
                   "--disable-data-logging", "--logs", logs, "--log-directly"], client=True)
    pipeline = StandardPipelineParser.pipeline_factory(args)
    api = IntegrationTestAPI(pipeline)
    api.setup()
    print(json.dumps({"ready": True}), flush=True)
    history = api.get_telemetry_test_history()
    events = api.get_event_test_history()
    deadline = time.monotonic() + float(seconds)
    try:
        while time.monotonic() < deadline:
            time.sleep(0.05)  # the API offers history polling, no blocking read
            for ch in history.retrieve_new():
                value = ch.get_val_obj().val
                print(json.dumps({"name": ch.template.get_full_name(), "id": ch.id,
                                  "t": ch.time.get_float(), "value": value}), flush=True)
                if command:
                    api.send_command(command.pop())
            for ev in events.retrieve_new():
                print(json.dumps({"event": ev.template.get_full_name(), "id": ev.id,
                                  "args": [a.val for a in ev.get_args()]}), flush=True)
    finally:
        api.teardown()
        pipeline.disconnect()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
