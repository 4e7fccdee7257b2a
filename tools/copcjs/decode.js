// Decode every node of a COPC file with the npm 'copc' reader (laz-perf in WebAssembly) and print
// one JSON object: the info VLR as it reads it, the WKT, and per node its key, the points it
// declares and decodes, and the sums of X, Y, Z (scaled) of the decoded points.
//     node tools/copcjs/decode.js FILE.copc.laz
// (npm install in tools/copcjs first: tests/test_export_copc.py does it, .ci/run too.)
const { Copc } = require('copc');

async function main(file) {
  const copc = await Copc.create(file);
  const { nodes, pages } = await Copc.loadHierarchyPage(file, copc.info.rootHierarchyPage);
  const out = {
    info: { cube: copc.info.cube, spacing: copc.info.spacing, gpsTimeRange: copc.info.gpsTimeRange },
    wkt: copc.wkt || null,
    pointFormat: copc.header.pointDataRecordFormat,
    pointCount: copc.header.pointCount,
    pages: Object.keys(pages).length,
    nodes: {},
  };
  for (const [key, node] of Object.entries(nodes)) {
    if (!node || node.pointCount === 0) continue;
    const view = await Copc.loadPointDataView(file, copc, node);
    const get = ['X', 'Y', 'Z'].map((d) => view.getter(d));
    const sums = [0, 0, 0];
    for (let i = 0; i < view.pointCount; i++) for (let a = 0; a < 3; a++) sums[a] += get[a](i);
    out.nodes[key] = { declared: node.pointCount, decoded: view.pointCount, sums };
  }
  process.stdout.write(JSON.stringify(out));
}

main(process.argv[2]).catch((e) => { process.stderr.write(String(e && e.stack || e) + '\n'); process.exit(1); });
