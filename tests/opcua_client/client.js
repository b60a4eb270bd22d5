// An independent OPC UA client (node-opcua) for the tests of the W-ARa OPC UA server.
//
//   node client.js SCENARIO URL CERT.pem KEY.pem PKI_DIR [USER PASSWORD]
//
// SCENARIO: "full" (browse to the Machinery and PackML nodes, subscribe to the attitude
// and the PackML state at 10 Hz, call StartAdjustment and Stop, see the state change),
// "session" (open a session only: for the refusals), "call-start" (call StartAdjustment
// only), "call-walk" (StartWalk with 0 steps, refused, then with 3). Prints one JSON object on stdout: {"ok": bool, "error": ..., ...}.
"use strict";
const {
  OPCUAClient,
  MessageSecurityMode,
  SecurityPolicy,
  UserTokenType,
  ClientSubscription,
  ClientMonitoredItem,
  AttributeIds,
  TimestampsToReturn,
  DataType,
  makeBrowsePath,
  BrowseDirection,
  StatusCodes,
} = require("node-opcua-client");
const { OPCUACertificateManager } = require("node-opcua-certificate-manager");

const [scenario, url, certFile, keyFile, pkiDir, user, password] = process.argv.slice(2);
const NS = "urn:wara:ipc";
const out = { ok: false, scenario };

function done(code) {
  console.log(JSON.stringify(out));
  process.exit(code);
}

async function main() {
  const certificateManager = new OPCUACertificateManager({
    rootFolder: pkiDir,
    automaticallyAcceptUnknownCertificate: true, // the server's: the test trusts it
  });
  await certificateManager.initialize();
  const client = OPCUAClient.create({
    applicationName: "wara-test-node-client",
    applicationUri: "urn:wara:test:node-client",
    securityMode: MessageSecurityMode.SignAndEncrypt,
    securityPolicy: SecurityPolicy.Basic256Sha256,
    certificateFile: certFile,
    privateKeyFile: keyFile,
    clientCertificateManager: certificateManager,
    endpointMustExist: false,
    connectionStrategy: { maxRetry: 0, initialDelay: 100, maxDelay: 200 },
    requestedSessionTimeout: 30000,
    // generous: the tests run on shared, loaded machines
    transportTimeout: 60000,
    defaultTransactionTimeout: 60000,
  });
  const t0 = Date.now();
  await client.connect(url);
  out.connected = true;
  const identity = user
    ? { type: UserTokenType.UserName, userName: user, password }
    : { type: UserTokenType.Anonymous };
  let session;
  try {
    session = await client.createSession(identity);
  } catch (err) {
    out.error = `session refused: ${err.message}`;
    await client.disconnect();
    return done(3);
  }
  out.session = true;
  const ns = (await session.readNamespaceArray()).indexOf(NS);
  const nsMach = (await session.readNamespaceArray()).indexOf("http://opcfoundation.org/UA/Machinery/");
  const nsPack = (await session.readNamespaceArray()).indexOf("http://opcfoundation.org/UA/PackML/");
  const nsDi = (await session.readNamespaceArray()).indexOf("http://opcfoundation.org/UA/DI/");
  const id = (s) => `ns=${ns};s=W-ARa.${s}`;
  const objectId = id("").slice(0, -1);

  async function call(name, args) {
    const r = await session.call({ objectId, methodId: id(name), inputArguments: args || [] });
    return { status: r.statusCode.name, output: (r.outputArguments || []).map((v) => v.value) };
  }

  if (scenario === "session") {
    out.ok = true;
  } else if (scenario === "call-start") {
    out.start = await call("StartAdjustment", [
      { dataType: DataType.Double, value: 0.01 },
      { dataType: DataType.Double, value: 0.02 },
    ]);
    out.ok = out.start.status === "Good";
  } else if (scenario === "call-walk") {
    out.refused = await call("StartWalk", [{ dataType: DataType.UInt32, value: 0 }]);
    out.walk = await call("StartWalk", [{ dataType: DataType.UInt32, value: 3 }]);
    out.ok = out.walk.status === "Good" && out.refused.status === "BadInvalidArgument";
  } else if (scenario === "call-packml") {
    // PackMLBaseObjectType's own methods on the PackML object
    const packml = id("PackML");
    const callOn = async (name, args) => {
      const r = await session.call({ objectId: packml, methodId: id(`PackML.${name}`), inputArguments: args });
      return { status: r.statusCode.name, output: (r.outputArguments || []).map((v) => v.value) };
    };
    out.unit_mode = await callOn("SetUnitMode", [{ dataType: DataType.Int32, value: 2 }]);
    out.bad_unit_mode = await callOn("SetUnitMode", [{ dataType: DataType.Int32, value: 9 }]);
    out.speed = await callOn("SetMachSpeed", [{ dataType: DataType.Float, value: 1.0 }]);
    out.ok =
      out.unit_mode.status === "Good" &&
      out.bad_unit_mode.status === "BadInvalidArgument" &&
      out.speed.status === "BadNotSupported";
  } else if (scenario === "full") {
    // browse by path, as a SCADA integrator would
    const machine = `/${nsMach}:Machines/${ns}:W-ARa`;
    const blocks = `${machine}/${nsMach}:MachineryBuildingBlocks`;
    const paths = {
      identification: `${machine}/${nsDi}:Identification/${nsDi}:Manufacturer`,
      item_state: `${blocks}/${nsMach}:MachineryItemState/CurrentState`,
      operation_mode: `${blocks}/${nsMach}:MachineryOperationMode/CurrentState`,
      packml_state: `${machine}/${nsPack}:PackML/${nsPack}:Status/${ns}:StateCurrent`,
      packml_unit_mode: `${machine}/${nsPack}:PackML/${nsPack}:Status/${nsPack}:UnitModeCurrent`,
      packml_base: `${machine}/${nsPack}:PackML/${nsPack}:BaseStateMachine/CurrentState`,
      packml_machine: `${machine}/${nsPack}:PackML/${nsPack}:BaseStateMachine/${nsPack}:MachineState/CurrentState`,
      packml_execute: `${machine}/${nsPack}:PackML/${nsPack}:BaseStateMachine/${nsPack}:MachineState/${nsPack}:ExecuteState/CurrentState`,
      packml_execute_id: `${machine}/${nsPack}:PackML/${nsPack}:BaseStateMachine/${nsPack}:MachineState/${nsPack}:ExecuteState/CurrentState/Id`,
      item_state_id: `${blocks}/${nsMach}:MachineryItemState/CurrentState/Id`,
    };
    out.browse = {};
    for (const [k, p] of Object.entries(paths)) {
      const r = await session.translateBrowsePath(makeBrowsePath("ObjectsFolder", p));
      if (r.statusCode !== StatusCodes.Good) throw new Error(`browse ${k}: ${r.statusCode.name}`);
      const dv = await session.read({ nodeId: r.targets[0].targetId, attributeId: AttributeIds.Value });
      const v = dv.value.value;
      // a NodeId as "<namespace URI's last part>:<id>", e.g. "PackML:28"
      const nsName = (i) => (i === nsPack ? "PackML" : i === nsMach ? "Machinery" : String(i));
      out.browse[k] =
        v && v.text !== undefined ? v.text : v && v.namespace !== undefined ? `${nsName(v.namespace)}:${v.value}` : v;
    }
    // the companion types of the objects, as a SCADA's type-based import finds them
    const typed = {
      identification: `${machine}/${nsDi}:Identification`,
      item_state: `${blocks}/${nsMach}:MachineryItemState`,
      operation_mode: `${blocks}/${nsMach}:MachineryOperationMode`,
      packml: `${machine}/${nsPack}:PackML`,
      packml_status: `${machine}/${nsPack}:PackML/${nsPack}:Status`,
      packml_execute: `${machine}/${nsPack}:PackML/${nsPack}:BaseStateMachine/${nsPack}:MachineState/${nsPack}:ExecuteState`,
    };
    out.types = {};
    for (const [k, p] of Object.entries(typed)) {
      const r = await session.translateBrowsePath(makeBrowsePath("ObjectsFolder", p));
      if (r.statusCode !== StatusCodes.Good) throw new Error(`browse ${k}: ${r.statusCode.name}`);
      const b = await session.browse({
        nodeId: r.targets[0].targetId,
        referenceTypeId: "HasTypeDefinition",
        browseDirection: BrowseDirection.Forward,
        includeSubtypes: true,
        resultMask: 0x3f,
      });
      const ref = b.references[0];
      const tns = ref.nodeId.namespace;
      out.types[k] = `${tns === nsMach ? "Machinery" : tns === nsPack ? "PackML" : tns}:${ref.browseName.name}`;
    }
    const eu = await session.read({ nodeId: id("Attitude.MeasuredRoll.EngineeringUnits"), attributeId: AttributeIds.Value });
    out.roll_unit = eu.value.value.displayName.text;

    const sub = ClientSubscription.create(session, {
      requestedPublishingInterval: 100,
      requestedLifetimeCount: 100,
      requestedMaxKeepAliveCount: 10,
      maxNotificationsPerPublish: 100,
      publishingEnabled: true,
      priority: 10,
    });
    const states = [];
    const rolls = [];
    const watch = (nodeId, sink) => {
      const item = ClientMonitoredItem.create(
        sub,
        { nodeId, attributeId: AttributeIds.Value },
        { samplingInterval: 100, discardOldest: true, queueSize: 10 },
        TimestampsToReturn.Both,
      );
      item.on("changed", (dv) => sink.push(dv.value.value));
      return item;
    };
    watch(id("PackML.Status.StateCurrent"), states);
    watch(id("Attitude.MeasuredRoll"), rolls);
    const waitFor = async (pred, ms) => {
      const end = Date.now() + ms;
      while (Date.now() < end) {
        if (pred()) return true;
        await new Promise((r) => setTimeout(r, 20));
      }
      return false;
    };
    await waitFor(() => states.length > 0 && rolls.length > 0, 5000);
    out.initial_state = states[states.length - 1];
    out.start = await call("StartAdjustment", [
      { dataType: DataType.Double, value: 0.01 },
      { dataType: DataType.Double, value: 0.02 },
    ]);
    out.saw_execute = await waitFor(() => states.includes(6), 5000);
    out.stop = await call("Stop");
    out.saw_idle_after = await waitFor(() => states.lastIndexOf(4) > states.indexOf(6), 5000);
    out.states = states;
    out.rolls = rolls.slice(0, 3);
    await sub.terminate();
    out.ok =
      out.start.status === "Good" && out.stop.status === "Good" && out.saw_execute && out.saw_idle_after;
  }
  out.elapsed_ms = Date.now() - t0;
  await session.close();
  await client.disconnect();
  done(out.ok ? 0 : 1);
}

main().catch((err) => {
  out.error = String(err && err.message ? err.message : err);
  done(2);
});
