// quietframe: render a Blender shot and denoise it in one Flamenco job.
//
// Needs Flamenco 3.3 or newer (the `exec` command runs the denoise). On 3.8 and newer a render
// task's progress counts its frames, as Flamenco's own job type does (frameCount, the third
// argument of author.Command; older Managers ignore it).
//
// Install: copy this file into the `scripts/` folder next to the `flamenco-manager`
// executable. A Manager of 3.7 or newer reads it when job types are asked for (refresh the
// Blender add-on); older ones read the folder once at start: restart those. "Render +
// quietframe denoise" then appears among the add-on's job types. The Workers that take `misc`
// tasks need the quietframe client (`pip install ".[client]"` from a checkout, or the wheel of
// docs/farm.md: no compiler, no GPU, no onnxruntime) and deploy/farm/retry_on_75.py.
//
// Per chunk of frames the job has a render task and a denoise task. A denoise task waits for
// its own chunk's render task and for the ones that render its pre-roll (the frames just
// before the chunk, sent to warm the temporal history) and, with a look-ahead, its post-roll
// (the `lookahead` frames just after it, sent so that the chunk's last frames see their later
// frames; not written): without those it could read a frame Blender is still writing.
// `--strict` fails the task when a frame of the chunk is missing (a render that wrote nothing)
// instead of denoising across the gap. `--cut` at the job's first frame starts the history
// there: the frames before it are not this job's renders (without it, --strict would fail the
// first chunk for its missing pre-roll); with a look-ahead, `--cut` at the frame after the
// job's last ends the last chunk's post-roll the same way.
//
// Failures: Flamenco fails a task on any non-zero exit and gives it to another Worker (up to
// the Manager's task_fail_after_softfail_count), blocklisting a Worker that fails
// blocklist_threshold tasks of the job. So the denoise runs under retry_on_75.py: exit 75
// (server unavailable or busy) is retried in place with growing waits (the rerun resumes),
// while 2 (configuration) and 3 (input) fail the task at once, with what to fix in its log.
//
// Progress: the denoise is one `exec` command, one step of the task (the Worker counts steps
// from Blender's output only; an exec command's output goes to the task log, unread). The
// client prints one line per frame there (`frame 1005 sh010.1005.exr done [5/12], 41 ms`).
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
    { key: "lookahead", type: "int32", default: 0, visible: "submission",
      description: "Later frames (0-4) each frame's denoise also uses; each chunk then reads "
        + "that many frames after it too (post-roll, not written). 0: none" },
    { key: "quietframe", type: "string", default: "quietframe", visible: "submission",
      description: "The quietframe client on the Workers" },
    { key: "retry_wrapper", type: "string", default: "/opt/quietframe/bin/retry_on_75.py",
      visible: "submission",
      description: "deploy/farm/retry_on_75.py on the Workers: retries exit 75 (server busy), "
        + "fails 2/3 (fix the job) at once. Empty: quietframe runs directly" },
    { key: "python", type: "string", default: "python3", visible: "submission",
      description: "The Python 3 that runs retry_on_75.py on the Workers" },

    // Automatically evaluated settings:
    { key: "blendfile", type: "string", required: true, visible: "web",
      description: "Path of the Blend file to render" },
    { key: "scene", type: "string", required: true, eval: "C.scene.name", visible: "web",
      description: "Name of the scene to render" },
  ],
};

// Render settings forced the way Flamenco's own Blender job type forces them (since 3.9 the job
// type does it, no longer the add-on): the file extension on, as the output pattern passed
// below has none, and no placeholder files (an empty file where a frame belongs). Unlike
// Flamenco's own (which renders each job into a new timestamped folder and so skips frames on
// disk) existing frames are overwritten: this job type's pattern is reused from one submission
// to the next, and a frame kept from an earlier render would be denoised as this one's.
const RENDER_SETTINGS = [
  "import bpy",
  "render = bpy.context.scene.render",
  "render.use_file_extension = True",
  "render.use_overwrite = True",
  "render.use_placeholder = False",
].join("; ");

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
  const lookahead = settings.lookahead || 0;
  if (lookahead < 0 || lookahead > 4) {
    throw "lookahead takes 0 to 4 frames";
  }
  // where the job's history starts, and the frame after its last (no post-roll beyond it)
  const bounds = [chunkBounds(chunks[0])[0], chunkBounds(chunks[chunks.length - 1])[1] + 1];
  for (const chunk of chunks) {
    const task = denoiseTask(settings, chunk, bounds, lookahead);
    const needed = rendersNeededBy(chunk, chunks, renders, settings.pre_roll, lookahead);
    for (const render of needed) {
      task.addDependency(render);
    }
    job.addTask(task);
  }
}

function renderTask(settings, chunk) {
  const task = author.Task(`render-${chunk}`, "blender");
  // --scene first: Blender applies its arguments in order, and a multi-scene .blend would
  // otherwise render the scene it was saved on.
  const args = settings.scene ? ["--scene", settings.scene] : [];
  task.addCommand(author.Command("blender-render", {
    exe: "{blender}",
    exeArgs: "{blenderArgs}",
    argsBefore: [],
    blendfile: settings.blendfile,
    args: args.concat([
      "--python-expr", RENDER_SETTINGS,
      // Blender adds the extension (use_file_extension, forced above).
      "--render-output", settings.render_output.replace(/\.exr$/i, ""),
      "--render-format", "OPEN_EXR_MULTILAYER",
      "--render-frame", chunk.replaceAll("-", ".."), // Blender's range notation
    ]),
  }, renderSteps(chunk)));
  return task;
}

// Frames in the chunk: the steps a Manager of 3.8 or newer counts from Blender's output; 0
// (a command without steps) where frameCount does not exist yet.
function renderSteps(chunk) {
  return typeof frameCount === "function" ? frameCount(chunk) : 0;
}

function denoiseTask(settings, chunk, bounds, lookahead) {
  const task = author.Task(`denoise-${chunk}`, "misc");
  let denoise = [settings.quietframe, "denoise", "--server", settings.server,
                 settings.render_output, "--out", settings.denoised_output, "--frames", chunk,
                 "--pre-roll", String(settings.pre_roll), "--cut", String(bounds[0]),
                 "--model", settings.model, "--strict"];
  if (lookahead > 0) {
    denoise = denoise.concat(["--lookahead", String(lookahead), "--post-roll",
                              String(lookahead), "--cut", String(bounds[1])]);
  }
  const command = settings.retry_wrapper
    ? { exe: settings.python, args: [settings.retry_wrapper, "--"].concat(denoise) }
    : { exe: denoise[0], args: denoise.slice(1) };
  task.addCommand(author.Command("exec", command));
  return task;
}

// The render tasks whose frames a chunk's denoise task reads: its own and those holding the
// `preRoll` frames before it and the `postRoll` frames after it.
function rendersNeededBy(chunk, chunks, renders, preRoll, postRoll) {
  const bounds = chunkBounds(chunk);
  const needed = [];
  chunks.forEach((other, i) => {
    const otherBounds = chunkBounds(other);
    if (otherBounds[1] >= bounds[0] - preRoll && otherBounds[0] <= bounds[1] + postRoll) {
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
