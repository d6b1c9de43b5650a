// MediaPipe's PoseLandmarker off the page's thread, so the page takes the server's
// answers while the model runs on the next frame. On the CPU (XNNPACK,
// WebAssembly): no WebGL model, which a browser without a GPU only emulates,
// slowly. Gets { init } once, then { frame: ImageBitmap, time } (the bitmap is
// closed here); answers { ready }, { landmarks (33 of {x, y, z, visibility}, or
// null), ms } or { error }.
import { FilesetResolver, PoseLandmarker } from "./vendor/mediapipe/vision_bundle.mjs";

const vendor = new URL("vendor/mediapipe/", self.location.href).href;
let landmarker = null;
self.onmessage = async ({ data }) => {
  try {
    if (data.init) {
      // The WebAssembly as an ES module (a module worker cannot importScripts); it has SIMD.
      landmarker = await PoseLandmarker.createFromOptions(await FilesetResolver.forVisionTasks(vendor.slice(0, -1), true), {
        baseOptions: { modelAssetPath: vendor + "pose_landmarker_lite.task", delegate: "CPU" },
        runningMode: "VIDEO",
        numPoses: 1,
        minPoseDetectionConfidence: 0.5,
        minPosePresenceConfidence: 0.5,
        minTrackingConfidence: 0.5,
      });
      self.postMessage({ ready: true });
      return;
    }
    const t0 = performance.now();
    const result = landmarker.detectForVideo(data.frame, data.time);
    data.frame.close();
    self.postMessage({ landmarks: result.landmarks[0] || null, ms: performance.now() - t0 });
  } catch (e) {
    if (data.frame) data.frame.close();
    self.postMessage({ error: e.message || String(e) });
  }
};
