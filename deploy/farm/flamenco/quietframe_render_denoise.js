// quietframe: render a Blender shot and denoise it in one Flamenco (v3) job.
//
// Install: copy this file into the `scripts/` folder next to the `flamenco-manager`
// executable and restart the Manager; "Render + quietframe denoise" then appears among the
// job types of the Blender add-on. The Workers that take `misc` tasks need the quietframe
// client (`pip install ".[client]"` from a checkout, or the wheel of docs/farm.md: no
// compiler, no GPU, no onnxruntime).
//
// Per chunk of frames the job has a render task and a denoise task. A denoise task waits for
// its own chunk's render task and for the ones that render its pre-roll (the frames just
// before the chunk, sent to warm the temporal history): without those it could read a frame
// Blender is still writing. `--strict` fails the task when a frame of the chunk is missing (a
// render that wrote nothing) instead of denoising across the gap. `--cut` at the job's first
// frame starts the history there: the frames before it are not this job's renders (without
// it, --strict would fail the first chunk for its missing pre-roll). A failed denoise task
// (exit 75: server busy or down) is retried by Flamenco; the rerun resumes.
//
// The scene must write multilayer EXR with the Denoising Data passes (View Layer properties >
// Passes > Data > Denoising Data): quietframe reads the noisy beauty, albedo, normal and depth
// from them. docs/farm.md has the rest.

const JOB_TYPE = {
  label: "Render + quietframe denoise",
  settings: [
    // Settings for artists to determine:
    { key: "frames", type: "string", required: true,
      eval: "f'{C.scene.frame_start}-{C.scene.frame_end}'",
      evalInfo: { showLinkButton: true, description: "Scene frame range" },
      description: "Frame range to render and denoise, e.g. '1001-1100'" },
    { key: "chunk_size", type: "int32", default: 12, visible: "submission",
      description: "Frames per render task and per denoise task" },
    { key: "render_output", type: "string", subtype: "file_path", required: true,
      visible: "submission",
      description: "Rendered frames as a pattern, e.g. /shots/sh010/render/sh010.####.exr" },
    { key: "denoised_output", type: "string", subtype: "dir_path", required: true,
      visible: "submission", description: "Folder for the denoised frames (same file names)" },
    { key: "server", type: "string", required: true, default: "http://denoise:8000",
      visible: "submission", description: "quietframe server URL" },
    { key: "model", type: "string", default: "auto", visible: "submission",
      description: "quietframe model, or auto (`quietframe models` lists them)" },
    { key: "pre_roll", type: "int32", default: 4, visible: "submission",
      description: "Frames sent before each chunk to warm the history (not written)" },
    { key: "quietframe", type: "string", default: "quietframe", visible: "submission",
      description: "The quietframe client on the Workers" },

    // Automatically evaluated settings:
    { key: "blendfile", type: "string", required: true, visible: "web",
      description: "Path of the Blend file to render" },
  ],
};

function compileJob(job) {
  const settings = job.settings;
  if (!/#+/.test(settings.render_output)) {
    throw "render_output needs a frame field (####), e.g. /shots/sh010/render/sh010.####.exr";
  }
  const chunks = frameChunker(settings.frames, settings.chunk_size);
  const renders = chunks.map((chunk) => renderTask(settings, chunk));
  for (const task of renders) {
    job.addTask(task);
  }
  const firstFrame = chunkBounds(chunks[0])[0];  // where the job's history starts
  for (const chunk of chunks) {
    const task = denoiseTask(settings, chunk, firstFrame);
    for (const render of rendersNeededBy(chunk, chunks, renders, settings.pre_roll)) {
      task.addDependency(render);
    }
    job.addTask(task);
  }
}

function renderTask(settings, chunk) {
  const task = author.Task(`render-${chunk}`, "blender");
  task.addCommand(author.Command("blender-render", {
    exe: "{blender}",
    exeArgs: "{blenderArgs}",
    argsBefore: [],
    blendfile: settings.blendfile,
    args: [
      // Blender adds the extension itself.
      "--render-output", settings.render_output.replace(/\.exr$/i, ""),
      "--render-format", "OPEN_EXR_MULTILAYER",
      "--render-frame", chunk.replaceAll("-", ".."), // Blender's range notation
    ],
  }));
  return task;
}

function denoiseTask(settings, chunk, firstFrame) {
  const task = author.Task(`denoise-${chunk}`, "misc");
  task.addCommand(author.Command("exec", {
    exe: settings.quietframe,
    args: ["denoise", "--server", settings.server, settings.render_output,
           "--out", settings.denoised_output, "--frames", chunk,
           "--pre-roll", String(settings.pre_roll), "--cut", String(firstFrame),
           "--model", settings.model, "--strict"],
  }));
  return task;
}

// The render tasks whose frames a chunk's denoise task reads: its own and those holding the
// `preRoll` frames before it.
function rendersNeededBy(chunk, chunks, renders, preRoll) {
  const bounds = chunkBounds(chunk);
  const needed = [];
  chunks.forEach((other, i) => {
    const otherBounds = chunkBounds(other);
    if (otherBounds[1] >= bounds[0] - preRoll && otherBounds[0] <= bounds[1]) {
      needed.push(renders[i]);
    }
  });
  return needed;
}

// [first, last] frame of a chunk as frameChunker writes them: "1001-1012", "1013,1014", "7".
// (No spread or destructuring: the Manager's JavaScript engine is not node.)
function chunkBounds(chunk) {
  const numbers = chunk.split(/[,-]|\.\./).filter((part) => part !== "").map(Number);
  return [Math.min.apply(null, numbers), Math.max.apply(null, numbers)];
}
