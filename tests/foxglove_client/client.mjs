// Drives Foxglove's own client (@foxglove/ws-protocol) against a live server and prints what it
// saw as JSON lines on stdout, for tests/test_foxglove.py:
//   node client.mjs URL [--want TOPIC ...] [--call SERVICE JSON | --call-unadvertised JSON]
//     [--set-wind X,Y,Z [--times N]] [--timeout S] [--crowd N [--crowd-skip TOPIC ...]] [--watch]
//     [--stall N] [--churn N] [--assets]
// {"serverInfo": …} first, then {"channels": […]} once every wanted topic is advertised, one
// {"message": {topic, schemaName, encoding, data (base64)}} per wanted topic (its first), the
// service call's {"response": …} or {"failure": …}, the parameter's {"parameters": …} and
// {"status": …} lines; exits 0 when all came, 1 on a timeout or a closed connection.
// --times N sends the wind N times in one setParameters message.
// --stall N: N clients subscribe to the wanted topics, then never read again (their sockets
// paused): {"stalled": N, "ports": [each client's local port]} once all subscribed, then they
// wait until SIGTERM or SIGINT.
// --assets: once every wanted topic (/robot_description among them) has sent a message,
// fetchAsset every package:// URI the description names, all at once, as Foxglove's 3D panel
// does: one {"asset": {uri, status, error, bytes, sha256}} per answer, then
// {"fetched": {assets, seconds, streamed: {topic: messages during the burst}}}; the run also
// waits for every answer.
// --churn N: subscribe to every channel and unsubscribe again, N times, then {"churned": N}
// and stay connected until SIGTERM or SIGINT.
import wsProtocol from "@foxglove/ws-protocol";
const { FoxgloveClient } = wsProtocol;
import { WebSocket } from "ws";
import { createHash } from "node:crypto";

const args = process.argv.slice(2);
const url = args[0];
const want = [];
let call = null;
let wind = null;
let timeout = 30;
let crowd = 0;
let watch = false;
let times = 1;
let stall = 0;
let churn = 0;
let assets = false;
const crowdSkips = [];
for (let i = 1; i < args.length; i++) {
  if (args[i] === "--want") want.push(args[++i]);
  else if (args[i] === "--call") call = { name: args[++i], body: args[++i] };
  else if (args[i] === "--call-unadvertised") call = { raw: true, body: args[++i] };
  else if (args[i] === "--set-wind") wind = args[++i].split(",").map(Number);
  else if (args[i] === "--timeout") timeout = Number(args[++i]);
  else if (args[i] === "--crowd") crowd = Number(args[++i]);
  else if (args[i] === "--watch") watch = true;
  else if (args[i] === "--times") times = Number(args[++i]);
  else if (args[i] === "--stall") stall = Number(args[++i]);
  else if (args[i] === "--churn") churn = Number(args[++i]);
  else if (args[i] === "--assets") assets = true;
  else if (args[i] === "--crowd-skip") crowdSkips.push(args[++i]);
}
const out = (o) => process.stdout.write(JSON.stringify(o) + "\n");
// exit once stdout has taken every line (a pipe is written asynchronously)
const finish = (code) => process.stdout.write("", () => process.exit(code));
const protocols = [FoxgloveClient.SUPPORTED_SUBPROTOCOL, "foxglove.sdk.v1"];
if (watch) {
  // --watch: subscribe to every channel and count what arrives per topic (messages, bytes)
  // until SIGTERM or SIGINT, then print {"counts": {topic: [messages, bytes]}, "seconds": S}
  const started = Date.now();
  const counts = {};
  const c = new FoxgloveClient({ ws: new WebSocket(url, protocols) });
  const topics = new Map();
  c.on("advertise", (list) => {
    for (const ch of list) topics.set(c.subscribe(ch.id), ch.topic);
    out({ watching: list.length });
  });
  c.on("message", ({ subscriptionId, data }) => {
    const topic = topics.get(subscriptionId);
    const n = counts[topic] || [0, 0];
    counts[topic] = [n[0] + 1, n[1] + data.byteLength];
  });
  c.on("error", (e) => out({ error: String(e && e.message ? e.message : e) }));
  const report = () => {
    out({ counts, seconds: (Date.now() - started) / 1000 });
    finish(0);
  };
  process.on("SIGTERM", report);
  process.on("SIGINT", report);
} else if (stall > 0) {
  let ready = 0;
  const ports = [];
  for (let i = 0; i < stall; i++) {
    const ws = new WebSocket(url, protocols);
    const c = new FoxgloveClient({ ws });
    let done = false;
    c.on("advertise", (list) => {
      if (done || !want.every((t) => list.some((ch) => ch.topic === t))) return;
      done = true;
      for (const ch of list) if (want.includes(ch.topic)) c.subscribe(ch.id);
      // the subscription is sent; from now on nothing is read (ws resumes a paused socket
      // once its parser drains: that resume is disabled)
      ws.pause();
      ws._socket.pause();
      ws._socket.resume = () => ws._socket;
      ports.push(ws._socket.localPort);
      if (++ready === stall) out({ stalled: ready, ports });
    });
    c.on("error", () => {});
  }
  // paused sockets keep no event pending: without this timer Node would exit at once
  setInterval(() => {}, 1 << 30);
  const end = () => finish(0);
  process.on("SIGTERM", end);
  process.on("SIGINT", end);
} else if (churn > 0) {
  const c = new FoxgloveClient({ ws: new WebSocket(url, protocols) });
  let done = false;
  c.on("advertise", (list) => {
    if (done) return;
    done = true;
    for (let i = 0; i < churn; i++) {
      const ids = list.map((ch) => c.subscribe(ch.id));
      for (const id of ids) c.unsubscribe(id);
    }
    // one more subscription to everything, so the stop finds feeds running
    for (const ch of list) c.subscribe(ch.id);
    out({ churned: churn });
  });
  c.on("error", () => {});
  const end = () => finish(0);
  process.on("SIGTERM", end);
  process.on("SIGINT", end);
} else if (crowd > 0) {
  // --crowd N: N clients at once, each subscribing to every channel but the skipped ones, then
  // all gone (half of
  // them in the middle of a message: the socket destroyed without a close handshake)
  let ready = 0;
  const sockets = [];
  for (let i = 0; i < crowd; i++) {
    const ws = new WebSocket(url, protocols);
    sockets.push(ws);
    const c = new FoxgloveClient({ ws });
    c.on("advertise", (list) => {
      for (const ch of list) if (!crowdSkips.includes(ch.topic)) c.subscribe(ch.id);
      if (++ready === crowd) {
        sockets.forEach((s, j) => (j % 2 ? s.terminate() : s.close()));
        out({ crowd: ready });
        finish(0);
      }
    });
    c.on("error", () => {});
  }
  setTimeout(() => {
    out({ timeout: { crowd: ready } });
    finish(1);
  }, timeout * 1000);
} else {
  run();
}
function run() {
const client = new FoxgloveClient({ ws: new WebSocket(url, protocols) });
const channels = new Map();
const subs = new Map();
const got = new Set();
let pending = (call ? 1 : 0) + (wind ? 1 : 0);
let services = [];
// --assets: {requestId: uri} of the fetches not yet answered; null until they are sent
let fetching = null;
let fetchStarted = 0;
let fetchCount = 0;
let description = null;
const streamed = {};
const done = () => {
  if (got.size === want.length && pending === 0 && (!assets || (fetching && fetching.size === 0))) {
    client.close();
    finish(0);
  }
};
setTimeout(() => {
  out({ timeout: { missing: want.filter((t) => !got.has(t)), pending, unanswered: fetching ? fetching.size : null } });
  finish(1);
}, timeout * 1000);
client.on("error", (e) => out({ error: String(e && e.message ? e.message : e) }));
client.on("close", () => {
  out({ closed: true });
  finish(1);
});
client.on("serverInfo", (info) => out({ serverInfo: info }));
client.on("status", (s) => out({ status: s }));
client.on("advertise", (list) => {
  for (const c of list) channels.set(c.id, c);
  const topics = new Set([...channels.values()].map((c) => c.topic));
  if (!want.every((t) => topics.has(t))) return;
  out({ channels: [...channels.values()].map((c) => ({ topic: c.topic, encoding: c.encoding, schemaName: c.schemaName, schemaEncoding: c.schemaEncoding })) });
  for (const c of channels.values()) {
    if (want.includes(c.topic) && ![...subs.values()].includes(c.id)) subs.set(client.subscribe(c.id), c.id);
  }
  if (wind) client.setParameters(Array.from({ length: times }, () => ({ name: "wind", value: wind, type: "float64_array" })), "set");
  if (call && call.raw) {
    // no service advertised (a read-only server): ask anyway, the server must refuse
    client.sendServiceCallRequest({ serviceId: 1, callId: 1, encoding: "json", data: new DataView(new TextEncoder().encode(call.body).buffer) });
  }
  done();
});
client.on("advertiseServices", (list) => {
  services = services.concat(list);
  out({ services: list.map((s) => s.name) });
  if (!call) return;
  const service = list.find((s) => s.name === call.name);
  if (!service) return;
  client.sendServiceCallRequest({ serviceId: service.id, callId: 1, encoding: "json", data: new DataView(new TextEncoder().encode(call.body).buffer) });
});
client.on("serviceCallResponse", (r) => {
  out({ response: new TextDecoder().decode(r.data) });
  pending--;
  done();
});
client.on("serviceCallFailure", (f) => {
  out({ failure: f.message });
  pending--;
  done();
});
client.on("parameterValues", (p) => {
  out({ parameters: p.parameters });
  pending--;
  done();
});
client.on("fetchAssetResponse", (r) => {
  if (!fetching || !fetching.has(r.requestId)) return;
  const uri = fetching.get(r.requestId);
  fetching.delete(r.requestId);
  const bytes = r.status === 0 ? Buffer.from(r.data.buffer, r.data.byteOffset, r.data.byteLength) : Buffer.alloc(0);
  out({ asset: { uri, status: r.status === 0 ? "success" : "error", error: r.error || null, bytes: bytes.length, sha256: createHash("sha256").update(bytes).digest("hex") } });
  if (fetching.size === 0) out({ fetched: { assets: fetchCount, seconds: (Date.now() - fetchStarted) / 1000, streamed } });
  done();
});
client.on("message", ({ subscriptionId, data }) => {
  const c = channels.get(subs.get(subscriptionId));
  if (!c) return;
  if (fetching && fetching.size > 0) streamed[c.topic] = (streamed[c.topic] || 0) + 1;
  if (got.has(c.topic)) return;
  got.add(c.topic);
  const bytes = Buffer.from(data.buffer, data.byteOffset, data.byteLength);
  if (c.topic === "/robot_description") description = JSON.parse(bytes.toString("utf8")).data;
  if (assets && !fetching && description !== null && got.size === want.length) {
    // every wanted topic flows: every mesh the description names, asked at once (the 3D
    // panel's burst)
    const text = description;
    const uris = [...new Set(text.match(/package:\/\/[^"'<>\s]+/g) || [])];
    fetching = new Map(uris.map((uri, i) => [i + 1, uri]));
    fetchCount = uris.length;
    fetchStarted = Date.now();
    for (const [id, uri] of fetching) client.fetchAsset(uri, id);
  }
  out({ message: { topic: c.topic, schemaName: c.schemaName, encoding: c.encoding, data: bytes.toString("base64") } });
  done();
});
}
