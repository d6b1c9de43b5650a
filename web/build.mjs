// Assembles dist/ (what `blapose-server --web-addr` serves at /): the page's own
// files from src/, the proto it speaks from ../proto, and the npm packages it
// runs (MediaPipe Pose with its WebAssembly and models, three.js, protobuf.js),
// so the page loads nothing but from the server. Run by `npm ci` (postinstall).
import { cpSync, mkdirSync, rmSync, existsSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";

const here = dirname(fileURLToPath(import.meta.url));
const dist = join(here, "dist");
const modules = join(here, "node_modules");
const copy = (from, to) => {
  if (!existsSync(from)) throw new Error(`missing ${from}: run npm ci in web/`);
  mkdirSync(dirname(to), { recursive: true });
  cpSync(from, to, { recursive: true });
};

rmSync(dist, { recursive: true, force: true });
copy(join(here, "src"), dist);
copy(join(here, "..", "proto", "blapose", "v1", "blapose.proto"), join(dist, "blapose.proto"));
copy(join(modules, "three", "build", "three.module.js"), join(dist, "vendor", "three", "three.module.js"));
copy(join(modules, "three", "build", "three.core.js"), join(dist, "vendor", "three", "three.core.js"));
copy(join(modules, "protobufjs", "dist", "protobuf.min.js"), join(dist, "vendor", "protobuf.min.js"));
// MediaPipe Pose: its loader, WebAssembly and the lite and full models (heavy is
// 27.7 MB and not offered).
const pose = join(modules, "@mediapipe", "pose");
for (const f of [
  "pose.js",
  "pose_solution_packed_assets.data",
  "pose_solution_packed_assets_loader.js",
  "pose_solution_simd_wasm_bin.data",
  "pose_solution_simd_wasm_bin.js",
  "pose_solution_simd_wasm_bin.wasm",
  "pose_solution_wasm_bin.js",
  "pose_solution_wasm_bin.wasm",
  "pose_web.binarypb",
  "pose_landmark_lite.tflite",
  "pose_landmark_full.tflite",
]) {
  copy(join(pose, f), join(dist, "vendor", "mediapipe", f));
}
console.log(`blapose live page assembled in ${dist}`);
