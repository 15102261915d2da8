// A client of the older generation, as @foxglove/ws-protocol's README writes one: the
// npm FoxgloveClient over the `ws` package, offering only its SUPPORTED_SUBPROTOCOL
// ("foxglove.websocket.v1").  Used by tests/test_foxglove_clients.py.
//
//   node foxglove_ws_client.js URL TOPIC COUNT TIMEOUT_S
//
// Prints one JSON line for the handshake ({"subprotocol": ...}), one per advertised topic
// set ({"topics": [...]}), then one per message of TOPIC ({"timestamp": ns, "data": {...}});
// exits 0 after COUNT messages, 1 on an error, a close or the timeout.
const { FoxgloveClient } = require("@foxglove/ws-protocol");
const { WebSocket } = require("ws");

const [url, topic, count, timeoutS] = process.argv.slice(2);
const want = Number(count);
const ws = new WebSocket(url, [FoxgloveClient.SUPPORTED_SUBPROTOCOL]);
const client = new FoxgloveClient({ ws });
const decoder = new TextDecoder();
const topics = new Set();
let subscription = null;
let got = 0;

function fail(why) {
  process.stderr.write(`${why}\n`);
  process.exit(1);
}

setTimeout(() => fail(`timeout: ${got} of ${want} messages of ${topic}`), Number(timeoutS) * 1000);
client.on("open", () => {
  console.log(JSON.stringify({ subprotocol: ws.protocol }));
});
client.on("error", (err) => fail(`error: ${err && err.message ? err.message : err}`));
client.on("close", (event) => fail(`closed: ${event && event.code}`));
client.on("advertise", (channels) => {
  for (const channel of channels) {
    topics.add(channel.topic);
    if (channel.topic === topic && subscription === null) {
      subscription = client.subscribe(channel.id);
    }
  }
  console.log(JSON.stringify({ topics: [...topics].sort() }));
});
client.on("message", ({ subscriptionId, timestamp, data }) => {
  if (subscriptionId !== subscription) {
    return;
  }
  const record = { timestamp: timestamp.toString(), data: JSON.parse(decoder.decode(data)) };
  console.log(JSON.stringify(record));
  if (++got >= want) {
    client.close();
    process.exit(0);
  }
});
