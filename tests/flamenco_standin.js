// A small stand-in for Flamenco's job compiler, after its documented job-type API: it loads a
// job type file, fills the settings' defaults, calls compileJob(job) with `author.Task`,
// `author.Command`, `task.addCommand`, `task.addDependency` and `job.addTask`, and prints the
// tasks it was given as JSON. Usage: node flamenco_standin.js JOB_TYPE.js SETTINGS_JSON
"use strict";
const fs = require("fs");
const vm = require("vm");

const [jobTypeFile, settingsJson] = process.argv.slice(2);
const tasks = [];

class Task {
    constructor(name, type) {
        this.name = name;
        this.type = type;
        this.commands = [];
        this.dependencies = [];
    }
    addCommand(command) {
        this.commands.push(command);
    }
    addDependency(task) {
        if (!(task instanceof Task)) throw new Error("addDependency takes a task");
        this.dependencies.push(task.name);
    }
}

const author = {
    Task: (name, type) => new Task(name, type),
    Command: (type, parameters) => ({type, parameters}),
};
const context = vm.createContext({author});
vm.runInContext(fs.readFileSync(jobTypeFile, "utf8") + "\nthis.JOB_TYPE = JOB_TYPE; this.compileJob = compileJob;",
                context, {filename: jobTypeFile});
const settings = JSON.parse(settingsJson);
for (const setting of context.JOB_TYPE.settings) {
    if (!(setting.key in settings) && "default" in setting) settings[setting.key] = setting.default;
    if (setting.required && !(setting.key in settings)) throw new Error(`missing required setting ${setting.key}`);
}
const job = {settings, addTask: (task) => tasks.push(task)};
try {
    context.compileJob(job);
} catch (error) {
    console.error(`compileJob: ${error}`);
    process.exit(2);
}
console.log(JSON.stringify({label: context.JOB_TYPE.label, settings: context.JOB_TYPE.settings.map((s) => s.key), tasks}));
