//! `esrp-dataset`: generate, validate, inspect and describe ESRP-Bench datasets.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Mutex;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use clap::{Parser, Subcommand};
use esrp_dataset::files::{Dataset, MANIFEST_SCHEMA, Manifest, write_manifest, write_scene};
use esrp_dataset::front::{ImportOptions, import};
use esrp_dataset::stats::Stats;
use esrp_dataset::{BenchVersion, Benchmark, DEFAULT_SEED, StartRule, check_start, horizon_for, validate_by_replay};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;

#[derive(Parser)]
#[command(name = "esrp-dataset", version, about = "ESRP-Bench: generate, validate and describe scene-pair datasets")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// A count of at least one (`--scenes 0` would write an empty dataset).
fn at_least_one(text: &str) -> std::result::Result<usize, String> {
    match text.parse::<usize>() {
        Ok(0) => Err("must be at least 1".into()),
        Ok(n) => Ok(n),
        Err(e) => Err(e.to_string()),
    }
}

#[derive(Subcommand)]
enum Command {
    /// Generate scenes of a built-in benchmark (esrp-bench-v2 unless --benchmark says) into a
    /// folder.
    Generate {
        /// Output folder (gets manifest.json and scenes/).
        #[arg(long)]
        out: PathBuf,
        /// How many scenes, at least 1 (default: all from --first to the end).
        #[arg(long, value_parser = at_least_one)]
        scenes: Option<usize>,
        /// Index of the first scene.
        #[arg(long, default_value_t = 0)]
        first: usize,
        #[command(flatten)]
        built_in: BuiltIn,
        /// Overwrite a folder that already holds a dataset.
        #[arg(long)]
        force: bool,
    },
    /// Check every scene of a dataset: schema, esrp-core validation and expert replay, and for
    /// esrp-bench-v2 scenes the start-pose rule (away from every object, SPEC §7).
    Validate {
        /// Dataset folder.
        dir: PathBuf,
    },
    /// Write statistics (JSON and PNG plots) of a dataset.
    Stats {
        /// Dataset folder.
        dir: PathBuf,
        /// Output folder for stats.json and the plots.
        #[arg(long)]
        out: PathBuf,
    },
    /// Import rooms of 3D-FRONT (with 3D-FUTURE models) as scene pairs, by backward construction.
    #[command(name = "import-3dfront")]
    Import3dFront {
        /// Folder of 3D-FRONT house JSON files.
        #[arg(long)]
        front: PathBuf,
        /// The 3D-FUTURE-model folder (or its parent), with model_info.json.
        #[arg(long)]
        future: PathBuf,
        /// Output folder (gets manifest.json and scenes/).
        #[arg(long)]
        out: PathBuf,
        /// Seed for the choice of movable pieces and the backward construction.
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Import at most this many houses (at least 1).
        #[arg(long, value_parser = at_least_one)]
        max_houses: Option<usize>,
        /// Overwrite a folder that already holds a dataset.
        #[arg(long)]
        force: bool,
    },
    /// Render a scene's start ego view, goal view and current top-down view as PNG, or a
    /// contact sheet of many scenes' goal images.
    #[cfg(feature = "render")]
    Render {
        /// Scene id or benchmark index (with --dataset: an id of that dataset).
        #[arg(long, required_unless_present = "sheet")]
        scene: Option<String>,
        /// Instead: a contact sheet (sheet.png) of the goal images of the first N scenes (N at
        /// least 1).
        #[arg(long, conflicts_with = "scene", value_parser = at_least_one)]
        sheet: Option<usize>,
        /// Read scenes from this dataset folder instead of generating them.
        #[arg(long)]
        dataset: Option<PathBuf>,
        /// The built-in benchmark when generating (a scene id names its own).
        #[arg(long, default_value_t = BenchVersion::default(), value_parser = parse_version)]
        benchmark: BenchVersion,
        /// Benchmark seed when generating.
        #[arg(long, default_value_t = DEFAULT_SEED)]
        seed: u64,
        /// Image side in pixels.
        #[arg(long, default_value_t = 128)]
        resolution: u32,
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
    },
    /// Generate every scene of a built-in benchmark into one scene pack (the file the server
    /// ships: `server/service/packs/`), or with --check, regenerate them and compare them with a
    /// pack, byte for byte.
    Pack {
        /// The pack to write (or, with --check, to compare).
        #[arg(long)]
        out: PathBuf,
        #[command(flatten)]
        built_in: BuiltIn,
        /// Compare the pack at --out with the generator's scenes instead of writing it.
        #[arg(long)]
        check: bool,
    },
    /// Print one scene as JSON: from a dataset folder, or generated from the built-in benchmark.
    Show {
        /// Scene id (e.g. esrp-bench-v2/00042) or index into the built-in benchmark.
        id: String,
        /// Read the scene from this dataset folder instead of generating it.
        #[arg(long)]
        dataset: Option<PathBuf>,
        /// The built-in benchmark of an index (a scene id names its own).
        #[arg(long, default_value_t = BenchVersion::default(), value_parser = parse_version)]
        benchmark: BenchVersion,
        /// Benchmark seed when generating.
        #[arg(long, default_value_t = DEFAULT_SEED)]
        seed: u64,
    },
}

/// `esrp-dataset pack`: every scene of the benchmark generated (in parallel), then written as one
/// pack, or with `check` compared with the pack at `out`. Returns whether the check passed.
fn pack(out: &Path, version: BenchVersion, seed: u64, check: bool) -> Result<bool> {
    use esrp_dataset::pack::{ScenePack, scene_json, write_pack};
    let bench = Benchmark::new(version, seed);
    // Generating every scene takes minutes: a pack that cannot be compared, or an --out that
    // cannot be written, is reported before.
    let existing = if check {
        let bytes = std::fs::read(out).with_context(|| format!("reading {}", out.display()))?;
        let pack = ScenePack::parse(&bytes)?;
        if !pack.serves(&bench) {
            println!(
                "{}: holds {:?}, not every scene of {} from this generator",
                out.display(),
                pack.header(),
                bench.name()
            );
            return Ok(false);
        }
        Some(bytes)
    } else {
        if out.is_dir() {
            bail!("{} is a folder: --out names the pack file", out.display());
        }
        if let Some(dir) = out.parent().filter(|dir| !dir.as_os_str().is_empty()) {
            std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
        }
        None
    };
    let started = Instant::now();
    let bar = progress(bench.len(), "generate");
    let scenes: Vec<String> = (0..bench.len())
        .into_par_iter()
        .map(|index| {
            let generated = bench.generate(index).map(|g| scene_json(&g.scene));
            bar.inc(1);
            generated.map_err(|e| anyhow::anyhow!("scene {index}: {e}"))
        })
        .collect::<Result<_>>()?;
    bar.finish_and_clear();
    let Some(bytes) = existing else {
        let mut bytes = Vec::new();
        write_pack(&bench, &scenes, &mut bytes)?;
        esrp_dataset::files::write_atomic(out, &bytes)?;
        println!(
            "{}: {} scenes of {} in {} bytes ({:.0} s)",
            out.display(),
            scenes.len(),
            bench.name(),
            bytes.len(),
            started.elapsed().as_secs_f64()
        );
        return Ok(true);
    };
    let pack = ScenePack::parse(&bytes)?;
    let differing: Vec<usize> =
        (0..scenes.len()).filter(|&i| pack.json(i).map_or(true, |json| json != scenes[i])).collect();
    if differing.is_empty() {
        println!("{}: all {} scenes equal the generator's, byte for byte", out.display(), scenes.len());
    } else {
        println!(
            "{}: {} scenes differ from the generator's, first {:?}",
            out.display(),
            differing.len(),
            &differing[..differing.len().min(10)]
        );
    }
    Ok(differing.is_empty())
}

/// Which built-in benchmark a command generates, and on how many threads.
#[derive(clap::Args)]
struct BuiltIn {
    /// The built-in benchmark: esrp-bench-v2 (the agent starts away from the objects) or
    /// esrp-bench-v1 (it starts at the generator's last release; kept unchanged for published
    /// results).
    #[arg(long, default_value_t = BenchVersion::default(), value_parser = parse_version)]
    benchmark: BenchVersion,
    /// Benchmark seed (0 is the published benchmark itself).
    #[arg(long, default_value_t = DEFAULT_SEED)]
    seed: u64,
    /// Worker threads (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
}

impl BuiltIn {
    /// Sizes the worker pool (`--threads`) and returns the benchmark and its seed.
    fn start(&self) -> (BenchVersion, u64) {
        if let Some(threads) = self.threads {
            // Only fails if a pool was already built, which cannot happen here.
            let _ = rayon::ThreadPoolBuilder::new().num_threads(threads).build_global();
        }
        (self.benchmark, self.seed)
    }
}

fn parse_version(name: &str) -> Result<BenchVersion, String> {
    name.parse().map_err(|e: esrp_dataset::UnknownBenchmark| e.to_string())
}

fn progress(len: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len as u64);
    bar.set_style(
        ProgressStyle::with_template("{prefix} [{elapsed_precise}] {wide_bar} {pos}/{len} ({per_sec}, eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_prefix(what.to_owned());
    bar
}

fn generate(
    out: &Path,
    scenes: Option<usize>,
    first: usize,
    version: BenchVersion,
    seed: u64,
    force: bool,
) -> Result<bool> {
    let bench = Benchmark::new(version, seed);
    if first >= bench.len() {
        bail!("--first {first} is past the end: the benchmark has {} scenes (0..{})", bench.len(), bench.len());
    }
    let count = scenes.unwrap_or(bench.len() - first);
    if first.checked_add(count).is_none_or(|end| end > bench.len()) {
        bail!("--first {first} --scenes {count} runs past the benchmark's {} scenes", bench.len());
    }
    if out.join("manifest.json").exists() && !force {
        bail!("{} already holds a dataset (manifest.json): choose another --out or pass --force", out.display());
    }
    // Made now: an --out that cannot be written fails here, not once per scene after every
    // scene was generated.
    let scenes_dir = out.join("scenes");
    std::fs::create_dir_all(&scenes_dir).with_context(|| format!("cannot create {}", scenes_dir.display()))?;
    // What a run stopped between a write and its rename left behind.
    let stale = esrp_dataset::files::remove_stale_temporaries(&scenes_dir);
    if stale > 0 {
        eprintln!("removed {stale} temporary file(s) a stopped run left in {}", scenes_dir.display());
    }
    let started = Instant::now();
    let bar = progress(count, "generate");
    let rejections: Mutex<BTreeMap<String, usize>> = Mutex::new(BTreeMap::new());
    let starts: Mutex<Vec<esrp_dataset::StartReport>> = Mutex::new(Vec::new());
    let results: Vec<(Result<esrp_dataset::files::ManifestEntry, String>, f64)> = (first..first + count)
        .into_par_iter()
        .map(|index| {
            let scene_started = Instant::now();
            let generated = bench.generate(index);
            let milliseconds = 1e3 * scene_started.elapsed().as_secs_f64();
            let result = match generated {
                Ok(generated) => {
                    if let Ok(mut totals) = rejections.lock() {
                        for (reason, n) in &generated.rejections {
                            *totals.entry((*reason).to_owned()).or_default() += n;
                        }
                    }
                    if let (Some(start), Ok(mut starts)) = (generated.start, starts.lock()) {
                        starts.push(start);
                    }
                    write_scene(out, &generated.scene).map_err(|e| e.to_string())
                }
                Err(failed) => Err(failed.to_string()),
            };
            bar.inc(1);
            (result, milliseconds)
        })
        .collect();
    bar.finish_and_clear();
    let mut times: Vec<f64> = results.iter().map(|(_, ms)| *ms).collect();
    times.sort_by(f64::total_cmp);
    let percentile = |p: f64| times.get(((times.len() as f64 - 1.0) * p).round() as usize).copied().unwrap_or(0.0);
    let mut entries = Vec::with_capacity(count);
    let mut failures = 0;
    for (result, _) in results {
        match result {
            Ok(entry) => entries.push(entry),
            Err(message) => {
                failures += 1;
                eprintln!("error: {message}");
            }
        }
    }
    let rejections = rejections.into_inner().unwrap_or_default();
    let manifest = Manifest {
        schema: MANIFEST_SCHEMA.to_owned(),
        name: bench.name(),
        generator: format!("esrp-dataset {}", env!("CARGO_PKG_VERSION")),
        seed: Some(seed),
        rejections: rejections.clone(),
        scenes: entries,
    };
    write_manifest(out, &manifest)?;
    let elapsed = started.elapsed().as_secs_f64();
    println!(
        "wrote {} scenes to {} in {:.1} s ({:.1} ms per scene, {} threads)",
        manifest.scenes.len(),
        out.display(),
        elapsed,
        1e3 * elapsed / count.max(1) as f64,
        rayon::current_num_threads()
    );
    println!(
        "one scene takes {:.1} ms median, {:.1} ms at the 90th percentile, {:.1} ms at most (rejected attempts included)",
        percentile(0.5),
        percentile(0.9),
        percentile(1.0)
    );
    let rejected: usize = rejections.values().sum();
    println!("rejected attempts: {rejected} {rejections:?}");
    let starts = starts.into_inner().unwrap_or_default();
    if !starts.is_empty() {
        print_generated_starts(&starts, bench.start_rule());
    }
    if failures > 0 {
        eprintln!("{failures} scene(s) could not be generated");
    }
    Ok(failures == 0)
}

/// Reports how the generated esrp-bench-v2 scenes' start poses were drawn: how many keep the rule's
/// clearance and how many are the farthest reachable, their mean distance, drive and search.
fn print_generated_starts(starts: &[esrp_dataset::StartReport], rule: &StartRule) {
    let n = starts.len() as f64;
    let fallbacks = starts.iter().filter(|s| s.fallback).count();
    let min_rule = rule.min_clearance;
    let coarse = rule.cells[0];
    println!(
        "start poses: {} of {} at least {min_rule} m from every object, {fallbacks} the farthest reachable \
         ({} within fetch reach); {:.2} m from the nearest object on average; drive {:.1} actions; search \
         {:.0} positions on average (at most {}), {} on a grid finer than {coarse} m",
        starts.len() - fallbacks,
        starts.len(),
        starts.iter().filter(|s| s.clearance <= esrp_core::Rules::default().fetch_reach).count(),
        starts.iter().map(|s| s.clearance).sum::<f64>() / n,
        starts.iter().map(|s| s.drive as f64).sum::<f64>() / n,
        starts.iter().map(|s| s.searched as f64).sum::<f64>() / n,
        starts.iter().map(|s| s.searched).max().unwrap_or(0),
        starts.iter().filter(|s| s.cell < coarse).count(),
    );
}

fn import_3dfront(front: &Path, future: &Path, out: &Path, options: &ImportOptions, force: bool) -> Result<bool> {
    if out.join("manifest.json").exists() && !force {
        bail!("{} already holds a dataset (manifest.json): choose another --out or pass --force", out.display());
    }
    let started = Instant::now();
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template("import [{elapsed_precise}] {wide_bar} {pos}/{len} houses (eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let report = import(front, future, options, &|done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })?;
    bar.finish_and_clear();
    if report.scenes.is_empty() {
        bail!(
            "no room of the {} rooms in {} house(s) could be imported (skipped: {:?}); nothing written",
            report.rooms_seen,
            report.houses,
            report.rooms_skipped
        );
    }
    // Every scene is written only now, after the whole import succeeded: a failed import
    // leaves no partial dataset behind.
    let mut entries = Vec::with_capacity(report.scenes.len());
    for scene in &report.scenes {
        entries.push(write_scene(out, scene)?);
    }
    let manifest = Manifest {
        schema: MANIFEST_SCHEMA.to_owned(),
        name: "3dfront".to_owned(),
        generator: format!("esrp-dataset {} import-3dfront", env!("CARGO_PKG_VERSION")),
        seed: Some(options.seed),
        rejections: report.rooms_skipped.clone(),
        scenes: entries,
    };
    write_manifest(out, &manifest)?;
    for warning in report.warnings.iter().take(20) {
        eprintln!("warning: {warning}");
    }
    if report.warnings.len() > 20 {
        eprintln!("... and {} more warnings", report.warnings.len() - 20);
    }
    println!(
        "imported {} of {} rooms from {} houses into {} in {:.1} s",
        report.rooms_imported,
        report.rooms_seen,
        report.houses,
        out.display(),
        started.elapsed().as_secs_f64()
    );
    println!("rooms skipped: {:?}", report.rooms_skipped);
    println!("objects dropped: {:?}; nudged apart: {}", report.objects_dropped, report.objects_nudged);
    Ok(true)
}

fn validate(dir: &Path) -> Result<bool> {
    let dataset = Dataset::open(dir)?;
    let entries = &dataset.manifest().scenes;
    if entries.is_empty() {
        eprintln!("{}: the manifest lists no scenes", dir.display());
        println!("0 of 0 scenes valid: the dataset holds no scenes");
        return Ok(false);
    }
    // The server finds a scene by its id: an id listed twice leaves one of them unreachable.
    let mut listed: BTreeMap<&str, usize> = BTreeMap::new();
    for entry in entries {
        *listed.entry(entry.id.as_str()).or_default() += 1;
    }
    let rule = StartRule::default();
    let bar = progress(entries.len(), "validate");
    // Each scene's failure, or for an esrp-bench-v2 scene, its start's distance to the objects.
    let outcomes: Vec<(String, Result<Option<f64>, String>)> = entries
        .par_iter()
        .map(|entry| {
            let outcome = match dataset.read_scene(entry) {
                Err(e) => Err(e.to_string()),
                Ok(scene) if scene.id != entry.id => {
                    Err(format!("the file holds scene {:?}, the manifest says {:?}", scene.id, entry.id))
                }
                Ok(_) if listed[entry.id.as_str()] > 1 => {
                    Err(format!("listed {} times in the manifest", listed[entry.id.as_str()]))
                }
                Ok(scene) => validate_by_replay(&scene).map_err(|e| e.to_string()).and_then(|()| {
                    check_horizon(&scene)?;
                    let start = match BenchVersion::of_scene_id(&scene.id) {
                        Some(BenchVersion::V2) => {
                            Some(check_start(&scene, &rule).map_err(|e| format!("start pose: {e}"))?)
                        }
                        _ => None,
                    };
                    entry_matches(entry, &scene)?;
                    Ok(start)
                }),
            };
            bar.inc(1);
            (entry.id.clone(), outcome)
        })
        .collect();
    bar.finish_and_clear();
    let failures: Vec<(&str, &str)> =
        outcomes.iter().filter_map(|(id, o)| o.as_ref().err().map(|e| (id.as_str(), e.as_str()))).collect();
    for (id, reason) in &failures {
        eprintln!("{id}: {reason}");
    }
    println!("{} of {} scenes valid", entries.len() - failures.len(), entries.len());
    let starts: Vec<(&str, f64)> =
        outcomes.iter().filter_map(|(id, o)| o.as_ref().ok().copied().flatten().map(|d| (id.as_str(), d))).collect();
    if !starts.is_empty() {
        print_fallback_starts(&starts, &rule);
    }
    Ok(failures.is_empty())
}

/// What a manifest entry says differently from its scene file (the server lists and splits a
/// folder's scenes by the manifest alone).
fn entry_matches(entry: &esrp_dataset::files::ManifestEntry, scene: &esrp_core::Scene) -> Result<(), String> {
    let fields = [
        ("room_type", entry.room_type.clone(), scene.room_type.clone()),
        ("difficulty", entry.difficulty.as_str().to_owned(), scene.difficulty.as_str().to_owned()),
        ("split", entry.split.as_str().to_owned(), scene.split.as_str().to_owned()),
        ("movable_objects", entry.movable_objects.to_string(), scene.movable_objects.len().to_string()),
        ("expert_length", entry.expert_length.to_string(), scene.expert_trajectory.len().to_string()),
    ];
    let differing: Vec<String> = fields
        .iter()
        .filter(|(_, manifest, file)| manifest != file)
        .map(|(field, manifest, file)| format!("the manifest says {field} {manifest}, the file {file}"))
        .collect();
    if differing.is_empty() { Ok(()) } else { Err(differing.join("; ")) }
}

/// The horizon rule of SPEC §5: a scene's horizon is twice its expert trajectory's length,
/// rounded up to a multiple of 50, and at least 200 steps.
fn check_horizon(scene: &esrp_core::Scene) -> Result<(), String> {
    let rule = horizon_for(scene.expert_trajectory.len());
    if scene.horizon == rule {
        return Ok(());
    }
    Err(format!(
        "horizon {} where the rule gives {rule} for an expert trajectory of {} actions (SPEC §5: twice \
         its length, rounded up to a multiple of 50, at least 200)",
        scene.horizon,
        scene.expert_trajectory.len()
    ))
}

/// Reports the esrp-bench-v2 starts that keep the rule only because no reachable pose is
/// [`StartRule::min_clearance`] away (the farthest was taken): how many, and each one's distance.
fn print_fallback_starts(starts: &[(&str, f64)], rule: &StartRule) {
    let reach = esrp_core::Rules::default().fetch_reach;
    let fallbacks: Vec<&(&str, f64)> = starts.iter().filter(|(_, d)| *d < rule.min_clearance).collect();
    println!(
        "start poses: {} of {} at least {} m from every object; {} the farthest reachable ({} within fetch reach, {reach} m)",
        starts.len() - fallbacks.len(),
        starts.len(),
        rule.min_clearance,
        fallbacks.len(),
        fallbacks.iter().filter(|(_, d)| *d <= reach).count(),
    );
    for (id, distance) in fallbacks {
        println!("  {id}: {distance:.3} m from the nearest object");
    }
}

fn stats(dir: &Path, out: &Path) -> Result<()> {
    let dataset = Dataset::open(dir)?;
    let mut stats = Stats::default();
    for entry in &dataset.manifest().scenes {
        stats.add(&dataset.read_scene(entry)?);
    }
    stats.write(out)?;
    println!("{}", serde_json::to_string_pretty(&stats)?);
    println!("wrote stats.json and plots to {}", out.display());
    Ok(())
}

fn show(id: &str, dataset: Option<&Path>, version: BenchVersion, seed: u64) -> Result<()> {
    println!("{}", load_scene(id, dataset, version, seed)?.to_json_pretty());
    Ok(())
}

/// A scene by id: read from a dataset folder, or generated from the built-in benchmark (by id,
/// whose prefix names the version, or by index into `version`).
fn load_scene(id: &str, dataset: Option<&Path>, version: BenchVersion, seed: u64) -> Result<esrp_core::Scene> {
    Ok(match dataset {
        Some(dir) => {
            Dataset::open(dir)?.scene_by_id(id).with_context(|| format!("no scene {id:?} in {}", dir.display()))??
        }
        None => {
            let bench = Benchmark::new(BenchVersion::of_scene_id(id).unwrap_or(version), seed);
            let index = match id.parse::<usize>() {
                Ok(i) if i < bench.len() => i,
                _ => bench.index_of(id).with_context(|| {
                    format!(
                        "{id:?} is not a scene of {} (ids {} to {})",
                        bench.name(),
                        bench.scene_id(0),
                        bench.scene_id(bench.len() - 1)
                    )
                })?,
            };
            bench.generate(index)?.scene
        }
    })
}

#[cfg(feature = "render")]
fn render(
    scene: Option<&str>,
    sheet: Option<usize>,
    dataset: Option<&Path>,
    version: BenchVersion,
    seed: u64,
    resolution: u32,
    out: &Path,
) -> Result<()> {
    use std::sync::Arc;

    use esrp_core::CompiledScene;
    use esrp_render::{Renderer, RendererConfig};

    let renderer = Renderer::new(RendererConfig::default())?;
    let compile = |scene: esrp_core::Scene| -> Result<Arc<CompiledScene>> { Ok(CompiledScene::shared(scene)?) };
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    if let Some(count) = sheet {
        let scenes: Vec<esrp_core::Scene> = match dataset {
            Some(dir) => {
                let data = Dataset::open(dir)?;
                data.manifest().scenes.iter().take(count).map(|e| data.read_scene(e)).collect::<Result<_, _>>()?
            }
            None => {
                let bench = Benchmark::new(version, seed);
                (0..count.min(bench.len()))
                    .into_par_iter()
                    .map(|i| bench.generate(i).map(|g| g.scene))
                    .collect::<Result<_, _>>()?
            }
        };
        let compiled = scenes.into_iter().map(compile).collect::<Result<Vec<_>>>()?;
        let columns = (compiled.len() as f64).sqrt().ceil().max(1.0) as u32;
        let png = esrp_render::goal_contact_sheet_png(&renderer, &compiled, resolution, columns)?;
        esrp_dataset::files::write_atomic(&out.join("sheet.png"), &png)?;
        println!("wrote {} ({} goal images, {columns} per row)", out.join("sheet.png").display(), compiled.len());
        return Ok(());
    }
    let id = scene.context("give --scene ID or --sheet N")?;
    let compiled = compile(load_scene(id, dataset, version, seed)?)?;
    let pngs = esrp_render::render_scene_pngs(&renderer, &compiled, resolution)?;
    for (name, bytes) in [("ego.png", &pngs.ego), ("goal.png", &pngs.goal), ("current.png", &pngs.current)] {
        esrp_dataset::files::write_atomic(&out.join(name), bytes)?;
    }
    println!("wrote ego.png, goal.png and current.png of {} to {}", compiled.scene().id, out.display());
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Generate { out, scenes, first, built_in, force } => {
            let (benchmark, seed) = built_in.start();
            generate(&out, scenes, first, benchmark, seed, force)
        }
        Command::Import3dFront { front, future, out, seed, max_houses, force } => {
            let options = ImportOptions { seed, max_houses, ..ImportOptions::default() };
            import_3dfront(&front, &future, &out, &options, force)
        }
        Command::Validate { dir } => validate(&dir),
        Command::Stats { dir, out } => stats(&dir, &out).map(|()| true),
        #[cfg(feature = "render")]
        Command::Render { scene, sheet, dataset, benchmark, seed, resolution, out } => {
            render(scene.as_deref(), sheet, dataset.as_deref(), benchmark, seed, resolution, &out).map(|()| true)
        }
        Command::Pack { out, built_in, check } => {
            let (benchmark, seed) = built_in.start();
            pack(&out, benchmark, seed, check)
        }
        Command::Show { id, dataset, benchmark, seed } => show(&id, dataset.as_deref(), benchmark, seed).map(|()| true),
    };
    match result {
        Ok(true) => ExitCode::SUCCESS,
        Ok(false) => ExitCode::FAILURE,
        Err(e) => {
            eprintln!("error: {}", error_text(&e));
            ExitCode::FAILURE
        }
    }
}

/// An error and its causes, each said once: a file error's text already ends with its I/O
/// error, which is also its cause.
fn error_text(error: &anyhow::Error) -> String {
    let mut text = error.to_string();
    for cause in error.chain().skip(1) {
        let cause = cause.to_string();
        if !text.contains(&cause) {
            text.push_str(": ");
            text.push_str(&cause);
        }
    }
    text
}
