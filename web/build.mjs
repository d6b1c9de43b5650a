// Assembles dist/ (what `blapose-server --web-addr` serves at /): the page's own
// files from src/, the proto it speaks from ../proto, and the npm packages it
// runs (MediaPipe's PoseLandmarker with its WebAssembly and model, three.js,
// protobuf.js), so the page loads nothing but from the server. Run by `npm ci`
// (postinstall).
import { cpSync, mkdirSync, rmSync, existsSync, writeFileSync } from "node:fs";
import { dirname, join } from "node:path";
import { fileURLToPath } from "node:url";
import { poseLandmarkerLiteTask } from "./pose-task.mjs";

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
// MediaPipe's PoseLandmarker (@mediapipe/tasks-vision): its module and its
// WebAssembly as an ES module (for the page's module worker; it runs the models
// on the CPU, XNNPACK, no WebGL).
const tasks = join(modules, "@mediapipe", "tasks-vision");
copy(join(tasks, "vision_bundle.mjs"), join(dist, "vendor", "mediapipe", "vision_bundle.mjs"));
for (const ext of [".js", ".wasm"]) {
  const f = "vision_wasm_module_internal" + ext;
  copy(join(tasks, "wasm", f), join(dist, "vendor", "mediapipe", f));
}
// Its model: tasks-vision ships none, so pose_landmarker_lite.task is put together
// from the two models the legacy @mediapipe/pose package ships (pose-task.mjs).
writeFileSync(
  join(dist, "vendor", "mediapipe", "pose_landmarker_lite.task"),
  poseLandmarkerLiteTask(join(modules, "@mediapipe", "pose")),
);
console.log(`blapose live page assembled in ${dist}`);
