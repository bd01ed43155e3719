// Pack a float binary-little-endian INRIA .ply into .spz with Niantic's reference packer
// (nianticlabs/spz compiled to WebAssembly as @adobe/spz), declaring the source frame RDF so the
// packer itself converts to the format's RUB axes. Usage: node make-spz.mjs in.ply out.spz VERSION
import fs from 'node:fs';
import createModule from '@adobe/spz';

const [input, output, version] = process.argv.slice(2);
const buf = fs.readFileSync(input);
const end = buf.indexOf('end_header\n') + 'end_header\n'.length;
const header = buf.subarray(0, end).toString('latin1').split('\n');
if (!header.includes('format binary_little_endian 1.0')) throw new Error('need a binary LE ply');
const n = Number(header.find(l => l.startsWith('element vertex')).split(' ')[2]);
const names = header.filter(l => l.startsWith('property float ')).map(l => l.split(' ')[2]);
const data = new Float32Array(buf.buffer.slice(buf.byteOffset + end, buf.byteOffset + end + n * names.length * 4));
const col = name => {
    const j = names.indexOf(name);
    if (j < 0) throw new Error(`missing ${name}`);
    return i => data[i * names.length + j];
};
const nRest = names.filter(s => s.startsWith('f_rest_')).length;
const degree = [0, 9, 24, 45].indexOf(nRest);
const perChannel = nRest / 3;
const get = Object.fromEntries(['x', 'y', 'z', 'scale_0', 'scale_1', 'scale_2', 'f_dc_0', 'f_dc_1',
    'f_dc_2', 'opacity', 'rot_0', 'rot_1', 'rot_2', 'rot_3'].map(s => [s, col(s)]));
const rest = Array.from({ length: nRest }, (_, k) => col(`f_rest_${k}`));
const cloud = {
    numPoints: n, shDegree: degree, antialiased: false, extensions: [],
    positions: new Float32Array(n * 3), scales: new Float32Array(n * 3),
    rotations: new Float32Array(n * 4), alphas: new Float32Array(n),
    colors: new Float32Array(n * 3), sh: new Float32Array(n * nRest)
};
for (let i = 0; i < n; i++) {
    ['x', 'y', 'z'].forEach((s, a) => { cloud.positions[i * 3 + a] = get[s](i); });
    [0, 1, 2].forEach(a => {
        cloud.scales[i * 3 + a] = get[`scale_${a}`](i);
        cloud.colors[i * 3 + a] = get[`f_dc_${a}`](i);
    });
    cloud.alphas[i] = get.opacity(i);
    // GaussianCloud rotations are x y z w; the .ply's rot_0..3 are w x y z.
    [1, 2, 3, 0].forEach((k, a) => { cloud.rotations[i * 4 + a] = get[`rot_${k}`](i); });
    // .ply f_rest is channel-major; spz's sh is coefficient-major with the channel inner.
    for (let c = 0; c < 3; c++) {
        for (let k = 0; k < perChannel; k++) {
            cloud.sh[i * nRest + k * 3 + c] = rest[c * perChannel + k](i);
        }
    }
}
const spz = await createModule();
const bytes = spz.saveSpzToBuffer(cloud, {
    version: Number(version), from: spz.CoordinateSystem.RDF, sh1Bits: 5, shRestBits: 4
});
fs.writeFileSync(output, bytes);
console.log(`${output}: ${n} Gaussians, SH degree ${degree}, version ${version}, ${bytes.length} bytes`);
