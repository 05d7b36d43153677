//! Dataset statistics (the paper's Fig. 4 and §IV-B): counts by room type, movable category,
//! difficulty and split, the clutter level — the sum over a scene's movable objects of the plan
//! distance between initial and target positions — and where the agent starts: its plan distance
//! to the nearest movable footprint and the index of the expert's first `fetch` (0 in
//! esrp-bench-v1, the length of the drive back in esrp-bench-v2), as JSON and as PNG plots.

use std::collections::BTreeMap;
use std::path::Path;

use esrp_core::{CompiledScene, Rules, Scene};
use plotters::prelude::*;
use serde::{Deserialize, Serialize};

use crate::files::{FilesError, write_atomic};

/// Width of one clutter histogram bin, metres.
pub const CLUTTER_BIN: f64 = 0.5;
/// Width of one start-distance histogram bin, metres.
pub const START_DISTANCE_BIN: f64 = 0.25;
/// Width of one first-fetch histogram bin, steps.
pub const FIRST_FETCH_BIN: usize = 5;

/// Statistics of a set of scenes.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Number of scenes.
    pub scenes: usize,
    /// Number of movable objects.
    pub movable_objects: usize,
    /// Scenes per room type.
    pub room_types: BTreeMap<String, usize>,
    /// Movable objects per category.
    pub categories: BTreeMap<String, usize>,
    /// Scenes per difficulty.
    pub difficulties: BTreeMap<String, usize>,
    /// Scenes per split.
    pub splits: BTreeMap<String, usize>,
    /// Scenes per number of movable objects.
    pub object_counts: BTreeMap<usize, usize>,
    /// Clutter histogram: scenes per bin of [`CLUTTER_BIN`] metres (key: bin's lower edge in
    /// centimetres).
    pub clutter_histogram: BTreeMap<u32, usize>,
    /// Mean clutter level, metres.
    pub mean_clutter: f64,
    /// Mean expert trajectory length, steps.
    pub mean_expert_length: f64,
    /// Mean fixed objects per scene.
    pub mean_fixed_objects: f64,
    /// Scenes per bin of [`START_DISTANCE_BIN`] metres of the start's plan distance to the
    /// nearest movable footprint (key: bin's lower edge in centimetres).
    #[serde(default)]
    pub start_distance_histogram: BTreeMap<u32, usize>,
    /// Mean plan distance from the agent's start to the nearest movable footprint, metres.
    #[serde(default)]
    pub mean_start_distance: f64,
    /// Scenes whose agent starts within fetch reach of a movable object.
    #[serde(default)]
    pub starts_within_reach: usize,
    /// The esrp-bench-v2 scenes whose start is closer to an object than the start rule's
    /// clearance ([`crate::StartRule::min_clearance`], 1.5 m): where no reachable pose is that
    /// far, the generator takes the farthest one (SPEC §7). Each scene's id and its start's
    /// distance to the nearest movable footprint, metres.
    #[serde(default)]
    pub fallback_starts: BTreeMap<String, f64>,
    /// Scenes per bin of [`FIRST_FETCH_BIN`] steps of the index of the expert's first `fetch`
    /// (key: bin's lower edge).
    #[serde(default)]
    pub first_fetch_histogram: BTreeMap<usize, usize>,
    /// Mean index of the expert's first `fetch` (the steps before it), steps.
    #[serde(default)]
    pub mean_first_fetch: f64,
}

/// The plan distance from the agent's start to the nearest movable object's footprint at its
/// initial pose (`None` if the scene does not compile; infinite without movable objects).
pub fn start_distance(scene: &Scene) -> Option<f64> {
    let compiled = CompiledScene::new(scene.clone(), Rules::default()).ok()?;
    let poses: Vec<_> = scene.movable_objects.iter().map(|o| o.pose).collect();
    Some(crate::start::object_clearance(&compiled, &poses, esrp_core::PlanPoint::new(scene.agent.x, scene.agent.z)))
}

/// The index of the expert trajectory's first `fetch` (its length if it has none).
pub fn first_fetch(scene: &Scene) -> usize {
    scene.expert_trajectory.iter().position(|a| *a == esrp_core::Action::Fetch).unwrap_or(scene.expert_trajectory.len())
}

/// The clutter level of a scene: the sum over movable objects of the plan distance between
/// their initial and target positions.
pub fn clutter(scene: &Scene) -> f64 {
    scene.movable_objects.iter().map(|o| o.pose.position().distance(o.target.position())).sum()
}

impl Stats {
    /// Adds one scene.
    pub fn add(&mut self, scene: &Scene) {
        self.scenes += 1;
        self.movable_objects += scene.movable_objects.len();
        *self.room_types.entry(scene.room_type.clone()).or_default() += 1;
        for o in &scene.movable_objects {
            *self.categories.entry(o.category.as_str().to_owned()).or_default() += 1;
        }
        *self.difficulties.entry(scene.difficulty.as_str().to_owned()).or_default() += 1;
        *self.splits.entry(scene.split.as_str().to_owned()).or_default() += 1;
        *self.object_counts.entry(scene.movable_objects.len()).or_default() += 1;
        let level = clutter(scene);
        let bin = ((level / CLUTTER_BIN).floor() * CLUTTER_BIN * 100.0).round() as u32;
        *self.clutter_histogram.entry(bin).or_default() += 1;
        let n = self.scenes as f64;
        self.mean_clutter += (level - self.mean_clutter) / n;
        self.mean_expert_length += (scene.expert_trajectory.len() as f64 - self.mean_expert_length) / n;
        self.mean_fixed_objects += (scene.fixed_objects.len() as f64 - self.mean_fixed_objects) / n;
        if let Some(distance) = start_distance(scene).filter(|d| d.is_finite()) {
            let bin = ((distance / START_DISTANCE_BIN).floor() * START_DISTANCE_BIN * 100.0).round() as u32;
            *self.start_distance_histogram.entry(bin).or_default() += 1;
            let measured = self.start_distance_histogram.values().sum::<usize>() as f64;
            self.mean_start_distance += (distance - self.mean_start_distance) / measured;
            if distance <= Rules::default().fetch_reach {
                self.starts_within_reach += 1;
            }
            if crate::BenchVersion::of_scene_id(&scene.id) == Some(crate::BenchVersion::V2)
                && distance < crate::StartRule::default().min_clearance
            {
                self.fallback_starts.insert(scene.id.clone(), distance);
            }
        }
        let fetch = first_fetch(scene);
        *self.first_fetch_histogram.entry(fetch / FIRST_FETCH_BIN * FIRST_FETCH_BIN).or_default() += 1;
        self.mean_first_fetch += (fetch as f64 - self.mean_first_fetch) / n;
    }

    /// Writes `stats.json` and the plots `room_types.png`, `categories.png`, `difficulty.png`,
    /// `clutter.png`, `start_distance.png` and `first_fetch.png` into `out`.
    pub fn write(&self, out: &Path) -> Result<(), StatsError> {
        std::fs::create_dir_all(out).map_err(|source| FilesError::Io { path: out.to_owned(), source })?;
        let mut json = serde_json::to_string_pretty(self).unwrap_or_default();
        json.push('\n');
        write_atomic(&out.join("stats.json"), json.as_bytes())?;
        register_font();
        let rooms: Vec<(String, usize)> = {
            let mut v: Vec<_> = self.room_types.iter().map(|(k, v)| (k.clone(), *v)).collect();
            v.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
            v
        };
        bar_chart(&out.join("room_types.png"), "Scenes per room type", &rooms, 1200)?;
        let categories: Vec<(String, usize)> = self.categories.iter().map(|(k, v)| (k.clone(), *v)).collect();
        bar_chart(&out.join("categories.png"), "Movable objects per category", &categories, 700)?;
        let difficulties: Vec<(String, usize)> = ["easy", "medium", "hard"]
            .iter()
            .map(|d| ((*d).to_owned(), self.difficulties.get(*d).copied().unwrap_or(0)))
            .collect();
        bar_chart(&out.join("difficulty.png"), "Scenes per difficulty", &difficulties, 500)?;
        let clutter: Vec<(String, usize)> =
            self.clutter_histogram.iter().map(|(k, v)| (format!("{:.1}", f64::from(*k) / 100.0), *v)).collect();
        bar_chart(
            &out.join("clutter.png"),
            "Scene clutter level (sum of initial-to-target distances, m)",
            &clutter,
            900,
        )?;
        let starts: Vec<(String, usize)> =
            self.start_distance_histogram.iter().map(|(k, v)| (format!("{:.2}", f64::from(*k) / 100.0), *v)).collect();
        bar_chart(
            &out.join("start_distance.png"),
            "Start: distance to the nearest movable object (m, bin lower edge)",
            &starts,
            900,
        )?;
        let fetches: Vec<(String, usize)> =
            self.first_fetch_histogram.iter().map(|(k, v)| (format!("{k}-{}", k + FIRST_FETCH_BIN - 1), *v)).collect();
        bar_chart(&out.join("first_fetch.png"), "Expert: steps before the first fetch", &fetches, 900)?;
        Ok(())
    }
}

/// A problem writing statistics.
#[derive(Debug, thiserror::Error)]
pub enum StatsError {
    /// Writing a file failed.
    #[error(transparent)]
    Files(#[from] FilesError),
    /// Drawing a plot failed.
    #[error("cannot draw {path}: {message}")]
    Plot {
        /// The plot's file.
        path: String,
        /// What went wrong.
        message: String,
    },
}

fn register_font() {
    // Registering twice is harmless; the font ships inside the binary (no system fonts needed).
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
}

/// A horizontal bar chart (labels on the left, read top to bottom) written as a PNG.
fn bar_chart(path: &Path, title: &str, bars: &[(String, usize)], _width: u32) -> Result<(), StatsError> {
    let plot_error =
        |e: &dyn std::fmt::Display| StatsError::Plot { path: path.display().to_string(), message: e.to_string() };
    let (width, height) = (900u32, (90 + 26 * bars.len().max(3)) as u32);
    let mut buffer = vec![0u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| plot_error(&e))?;
        let max = bars.iter().map(|b| b.1).max().unwrap_or(1).max(1);
        // Segment i is drawn from the top: the first bar is the top row.
        let n = bars.len();
        let labels: Vec<String> = bars.iter().map(|b| format!("{} ({})", b.0, b.1)).collect();
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 20))
            .margin(12)
            .x_label_area_size(30)
            .y_label_area_size(200)
            .build_cartesian_2d(0..(max + max / 8 + 1), (0..n).into_segmented())
            .map_err(|e| plot_error(&e))?;
        chart
            .configure_mesh()
            .disable_y_mesh()
            .y_labels(n.max(1))
            .y_label_formatter(&|v| match v {
                SegmentValue::CenterOf(i) if *i < n => labels[n - 1 - *i].clone(),
                _ => String::new(),
            })
            .label_style(("sans-serif", 14))
            .draw()
            .map_err(|e| plot_error(&e))?;
        chart
            .draw_series(
                Histogram::horizontal(&chart)
                    .style(RGBColor(70, 110, 170).filled())
                    .margin(3)
                    .data(bars.iter().enumerate().map(|(i, b)| (n - 1 - i, b.1))),
            )
            .map_err(|e| plot_error(&e))?;
        root.present().map_err(|e| plot_error(&e))?;
    }
    write_png(path, &buffer, width, height)
}

/// Encodes 8-bit RGB pixels as PNG and writes them atomically.
pub fn write_png(path: &Path, rgb: &[u8], width: u32, height: u32) -> Result<(), StatsError> {
    let plot_error = |message: String| StatsError::Plot { path: path.display().to_string(), message };
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, width, height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let mut writer = encoder.write_header().map_err(|e| plot_error(e.to_string()))?;
        writer.write_image_data(rgb).map_err(|e| plot_error(e.to_string()))?;
    }
    write_atomic(path, &bytes)?;
    Ok(())
}
