// A machine behind an OPC UA server of another stack (node-opcua), for tests/test_node_opcua.py.
// Usage: node server.js CONFIG.json. The config gives the port, the namespace URI, the samples to
// play (t_s, axis_mm, feed_mm_min and one column per sensor), the playback speed, the security
// (server certificate and key, trusted client certificates, user and password) and two files: the
// endpoint is written to `ready` once the server listens; every write to an output node is appended
// to `writes` as a JSON line {node, value, dataType, t_machine_s}.
"use strict";
const fs = require("fs");
const path = require("path");
const {
  OPCUAServer, OPCUACertificateManager, Variant, DataValue, DataType, StatusCodes, MessageSecurityMode, SecurityPolicy,
} = require("node-opcua");

async function main() {
  const cfg = JSON.parse(fs.readFileSync(process.argv[2], "utf8"));
  const pki = new OPCUACertificateManager({ rootFolder: cfg.pki, automaticallyAcceptUnknownCertificate: false });
  await pki.initialize();
  for (const c of cfg.trusted_clients) {
    fs.copyFileSync(c, path.join(cfg.pki, "trusted", "certs", path.basename(c)));
  }
  const server = new OPCUAServer({
    port: cfg.port,
    hostname: "127.0.0.1",
    resourcePath: "/sim",
    certificateFile: cfg.certificate,
    privateKeyFile: cfg.private_key,
    serverCertificateManager: pki,
    securityModes: [MessageSecurityMode.SignAndEncrypt],
    securityPolicies: [SecurityPolicy.Basic256Sha256],
    allowAnonymous: false,
    userManager: { isValidUser: (u, p) => u === cfg.user && p === process.env[cfg.password_env] },
    serverInfo: { applicationUri: cfg.application_uri },
  });
  await server.initialize();
  const space = server.engine.addressSpace;
  const ns = space.registerNamespace(cfg.uri);
  const cols = cfg.columns;
  const rows = cfg.samples;
  // the program starts when a client first reads an input. node-opcua calls each getter once while it
  // builds the address space, so reads count only once the server is listening: only a client that got
  // through the security checks can read, and the refused ones before it do not start the program
  let t0 = null;
  let listening = false;
  const now = () => (t0 === null ? 0 : ((Date.now() - t0) / 1000) * cfg.speed);
  // faults (machine time windows): a sensor column publishes a value (null: NaN) instead of its own;
  // during a freeze nothing new is published (the values and their timestamps stop)
  const faults = cfg.faults || { sensor: [], freeze: [] };
  const column = Object.fromEntries(cols.map((c, k) => [c.name, k]));
  const row = () => {
    let t = now();
    for (const f of faults.freeze) if (t >= f.from_s && t < f.to_s) t = f.from_s;
    let i = 0;
    while (i + 1 < rows.length && rows[i + 1][0] <= t) i++;
    const r = rows[i].slice();
    for (const f of faults.sensor) {
      if (r[0] >= f.from_s && r[0] < f.to_s) r[column[f.column]] = f.value === null ? NaN : f.value;
    }
    return r;
  };
  const last = rows[rows.length - 1][0];
  const objects = space.rootFolder.objects;
  const machine = ns.addObject({ organizedBy: objects, browseName: "Machine", nodeId: "s=Machine" });
  const axis = ns.addObject({ organizedBy: objects, browseName: "XAxis", nodeId: "s=X" });
  // each value carries its sample's machine time as its source timestamp (the program's start + t_s)
  const input = (name, k) => ns.addVariable({
    componentOf: axis, browseName: name, nodeId: `s=X.${name}`, dataType: "Double",
    value: {
      timestamped_get: () => {
        if (t0 === null && listening) t0 = Date.now();
        const r = row();
        return new DataValue({
          value: new Variant({ dataType: DataType.Double, value: r[k] }),
          sourceTimestamp: new Date(t0 + r[0] * 1000), serverTimestamp: new Date(),
        });
      },
    },
  });
  cols.forEach((c, k) => { if (k > 0) input(c.name, k); });
  ns.addVariable({
    componentOf: machine, browseName: "ProgramDone", nodeId: "s=Machine.ProgramDone", dataType: "Boolean",
    value: { get: () => new Variant({ dataType: DataType.Boolean, value: t0 !== null && now() > last + cfg.linger_s * cfg.speed }) },
  });
  const output = (name, dataType, initial) => {
    let current = initial;
    ns.addVariable({
      componentOf: axis, browseName: name, nodeId: `s=X.${name}`, dataType,
      accessLevel: "CurrentRead | CurrentWrite", userAccessLevel: "CurrentRead | CurrentWrite",
      value: {
        get: () => new Variant({ dataType: DataType[dataType], value: current }),
        set: (variant) => {
          if (variant.dataType !== DataType[dataType]) return StatusCodes.BadTypeMismatch;
          current = variant.value;
          fs.appendFileSync(cfg.writes, JSON.stringify({ node: name, value: current, dataType: DataType[variant.dataType], t_machine_s: now() }) + "\n");
          return StatusCodes.Good;
        },
      },
    });
  };
  output("TempComp_um", "Double", 0.0);
  output("TempComp_Status", "Int32", 0);
  await server.start();
  listening = true;
  fs.writeFileSync(cfg.ready + ".tmp", server.getEndpointUrl());
  fs.renameSync(cfg.ready + ".tmp", cfg.ready);
  const stop = async () => { await server.shutdown(100); process.exit(0); };
  process.on("SIGTERM", stop);
  process.on("SIGINT", stop);
}

main().catch((err) => { console.error(err); process.exit(1); });
