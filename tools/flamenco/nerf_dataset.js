// SPDX-License-Identifier: MIT
// A Flamenco job type: a NeRF dataset rendered by datasets_gen across the farm, then merged.
//
// Each of `shards` tasks runs `blender -b BLENDFILE --python .../datasets_gen/generate.py --
// FLAGS --out DATASET --shard K/N` (the views whose index % N == K, in every split); a last
// task, which depends on all of them, runs `--merge DATASET`. The workers must see the .blend,
// the dataset folder and datasets_gen at the same paths (Flamenco's shared storage).
//
// Install: copy this file into the Flamenco Manager's `scripts/` folder (beside its executable)
// and restart the Manager; the job type is then offered as "NeRF Dataset (datasets_gen)".

const JOB_TYPE = {
    label: "NeRF Dataset (datasets_gen)",
    description: "Render a nerf_synthetic dataset of the .blend with datasets_gen, split over the farm, then merge it",
    settings: [
        {key: "datasets_gen_root", type: "string", subtype: "dir_path", required: true,
         description: "The folder that holds datasets_gen/ on the workers (the repository, or the add-on's folder)"},
        {key: "out_dir", type: "string", subtype: "dir_path", required: true,
         description: "The dataset folder, on storage every worker shares"},
        {key: "shards", type: "int32", default: 4, propargs: {min: 1, max: 1000},
         description: "How many tasks share the views (datasets_gen --shard K/N)"},
        {key: "generator_args", type: "string", default: "",
         description: "datasets_gen's flags, separated by spaces (e.g. --resolution 800 --samples 128); not --out, --shard or --merge"},
        {key: "blendfile", type: "string", required: true, visible: "web",
         description: "The .blend to render"},
    ],
};

// Flags the job sets itself: a user's own would send the shards to different folders.
const RESERVED_FLAGS = ["--out", "--shard", "--merge", "--suite", "--resume"];

function compileJob(job) {
    const settings = job.settings;
    const shards = settings.shards;
    if (!Number.isInteger(shards) || shards < 1) {
        throw `shards must be a whole number of at least 1, got ${shards}`;
    }
    const extra = (settings.generator_args || "").trim().split(/\s+/).filter((arg) => arg !== "");
    const reserved = extra.filter((arg) => RESERVED_FLAGS.includes(arg.split("=")[0]));
    if (reserved.length > 0) {
        throw `generator_args: ${reserved.join(", ")} is set by the job itself`;
    }
    const script = joinPath(settings.datasets_gen_root, "datasets_gen", "generate.py");
    const renders = [];
    for (let index = 0; index < shards; index++) {
        const task = author.Task(`datasets_gen shard ${index + 1} of ${shards}`, "blender");
        task.addCommand(author.Command("blender-render", {
            exe: "{blender}",
            exeArgs: "{blenderArgs}",
            argsBefore: [],
            blendfile: settings.blendfile,
            args: ["--python", script, "--", ...extra, "--out", settings.out_dir,
                   "--shard", `${index}/${shards}`, "--no-progress"],
        }));
        job.addTask(task);
        renders.push(task);
    }
    // The merge is plain Python: Blender's own runs it, so the workers need nothing else.
    const merge = author.Task("datasets_gen merge", "blender");
    merge.addCommand(author.Command("exec", {
        exe: "{blender}",
        args: ["-b", "--factory-startup", "--python", script, "--", "--merge", settings.out_dir],
    }));
    for (const task of renders) {
        merge.addDependency(task);
    }
    job.addTask(merge);
}

function joinPath(...parts) {
    return parts.map((part, i) => (i === 0 ? part.replace(/[\\/]+$/, "") : part)).join("/");
}
