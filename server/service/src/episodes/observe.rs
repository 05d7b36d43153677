//! Observing an episode: which views an observation needs, the episode's last frames
//! ([`FrameCache`]), and the images put into the [`Observation`]. Creates, resets and steps all
//! observe through [`Observer::prepare`] → render what it asks for → [`Prepared::finish`].

use std::sync::Arc;

use bytes::Bytes;
use esrp_core::Episode;
use esrp_render::{Outputs, TopDownFrame, ViewOutput};

use crate::render::{DeviceScenes, View};
use crate::types::{Observation, SensorConfig};

/// What an episode's observations are made from, and the last ones made.
pub struct Observer {
    /// The scene's geometry on the renderers.
    pub scene: Arc<DeviceScenes>,
    /// The episode's sensors.
    pub sensors: SensorConfig,
    /// The goal image (RGB at the sensors' resolution), rendered once.
    pub goal: Bytes,
    /// Its pixel ↔ floor mapping.
    pub frame: TopDownFrame,
    /// The last observation's images, answered again by steps that change nothing they show.
    frames: FrameCache,
    /// The last top-down view made for watchers (`viewing`), shown again while nothing moved.
    watched_top_down: FrameCache,
}

/// An image a watcher's frame needs: one already made (the same pixels), or a view to render.
pub enum Shot {
    /// Made before: the episode's last observation, or the last watch frame's.
    Ready(Bytes),
    /// To render.
    Render(View),
}

impl Observer {
    /// An observer of `scene` with `sensors`, whose goal image is not rendered yet (see
    /// [`Observer::goal_view`]).
    pub fn new(scene: Arc<DeviceScenes>, sensors: SensorConfig) -> Self {
        let frame = scene.top_down_frame(sensors.resolution);
        Self {
            scene,
            sensors,
            goal: Bytes::new(),
            frame,
            frames: FrameCache::default(),
            watched_top_down: FrameCache::default(),
        }
    }

    /// The view of the goal image: the top-down view of `episode`'s target layout.
    pub fn goal_view(&self, episode: &Episode) -> View {
        let targets: Vec<esrp_core::ObjectPose> =
            episode.compiled().scene().movable_objects.iter().map(|o| o.target).collect();
        View::top_down(&self.scene, &targets, self.sensors.resolution)
    }

    /// The images a watcher of `episode` sees (`viewing`): its ego view as its client got it
    /// (RGB only), and with `top_down` the current top-down view at that side, with its frame.
    /// Each is taken from what was made before where that shows the same (the ego view of the
    /// episode's last observation; the last watch frame's top-down view while no object moved),
    /// else it is a view to render (then [`Observer::watched`] keeps the top-down view).
    pub fn watch_shots(&self, episode: &Episode, top_down: Option<u32>) -> (Shot, Option<(Shot, TopDownFrame)>) {
        let poses = episode.object_poses();
        let no_extras = Outputs { depth: false, segmentation: false };
        let ego = View::ego(&self.scene, episode.ego_camera(), poses, no_extras, self.sensors.resolution);
        // The observation's ego view may carry depth or segmentation too: its RGB is the same.
        let ego = match self.frames.lookup_where(|views| views.first().is_some_and(|v| same_pixels(v, &ego))) {
            Some(outputs) => outputs.into_iter().next().map_or(Shot::Render(ego), |o| Shot::Ready(o.rgb)),
            None => Shot::Render(ego),
        };
        let top = top_down.map(|side| {
            let view = View::top_down(&self.scene, poses, side);
            let shot = match self.watched_top_down.lookup(std::slice::from_ref(&view)) {
                Some(outputs) => outputs.into_iter().next().map_or(Shot::Render(view), |o| Shot::Ready(o.rgb)),
                None => Shot::Render(view),
            };
            (shot, self.scene.top_down_frame(side))
        });
        (ego, top)
    }

    /// Keeps `output` as the image of the watchers' top-down `view`, rendered for a watch frame.
    pub fn watched(&self, view: View, output: ViewOutput) {
        self.watched_top_down.store(vec![view], &[output]);
    }

    /// The views an observation of `episode` needs: the ego view, then the current top-down
    /// view if that sensor is on.
    fn views(&self, episode: &Episode) -> Vec<View> {
        let outputs = Outputs { depth: self.sensors.depth, segmentation: self.sensors.segmentation };
        let poses = episode.object_poses();
        let resolution = self.sensors.resolution;
        let mut views = vec![View::ego(&self.scene, episode.ego_camera(), poses, outputs, resolution)];
        if self.sensors.current_top_down {
            views.push(View::top_down(&self.scene, poses, resolution));
        }
        views
    }

    /// The observation of `episode` now, its images to come from [`Prepared::finish`]: the
    /// episode's last images if it shows what they show, else views to render.
    pub fn prepare(&self, episode: &Episode, include_goal: bool) -> Prepared {
        let views = self.views(episode);
        let images = match self.frames.lookup(&views) {
            Some(outputs) => Images::Reused(outputs),
            None => Images::Render { views, frames: self.frames.clone() },
        };
        let observation = Observation {
            resolution: self.sensors.resolution,
            grasping: episode.held().is_some(),
            goal_rgb: include_goal.then(|| self.goal.clone()),
            ..Default::default()
        };
        Prepared { observation, images, current_top_down: self.sensors.current_top_down }
    }
}

/// An observation whose images are to come: rendered, or the episode's last ones.
pub struct Prepared {
    observation: Observation,
    images: Images,
    current_top_down: bool,
}

/// Where an observation's images come from.
enum Images {
    /// Views to render, and the episode's cache, to keep the images with these views once they
    /// are rendered.
    Render { views: Vec<View>, frames: FrameCache },
    /// The episode's last images: nothing they show changed.
    Reused(Vec<ViewOutput>),
}

impl Prepared {
    /// The views to render for it (none when its images are reused).
    pub fn views(&self) -> &[View] {
        match &self.images {
            Images::Render { views, .. } => views,
            Images::Reused(_) => &[],
        }
    }

    /// How many images it reuses instead of rendering.
    pub fn reused(&self) -> usize {
        match &self.images {
            Images::Render { .. } => 0,
            Images::Reused(outputs) => outputs.len(),
        }
    }

    /// The observation with its images: the reused ones, or as many of `rendered` as
    /// [`Prepared::views`] asked for (in that order), which the episode keeps as its last
    /// images. The pixels move: RGB is the readback's `Bytes`, never copied.
    pub fn finish(self, rendered: &mut impl Iterator<Item = ViewOutput>) -> Observation {
        let Prepared { mut observation, images, current_top_down } = self;
        let outputs = match images {
            Images::Render { views, frames } => {
                let mine: Vec<ViewOutput> = rendered.take(views.len()).collect();
                frames.store(views, &mine);
                mine
            }
            Images::Reused(outputs) => outputs,
        };
        let mut outputs = outputs.into_iter();
        if let Some(ego) = outputs.next() {
            observation.depth = ego.depth;
            observation.segmentation = ego.segmentation;
            observation.ego_rgb = ego.rgb;
        }
        if current_top_down {
            observation.current_top_down = outputs.next().map(|v| v.rgb);
        }
        observation
    }
}

/// Whether two views draw the same pixels: the same scene upload, camera, object poses,
/// outputs and resolution are everything the renderer reads, and rendering is deterministic.
fn same_view(a: &View, b: &View) -> bool {
    Arc::ptr_eq(&a.scene, &b.scene)
        && a.camera == b.camera
        && a.poses == b.poses
        && a.outputs == b.outputs
        && a.resolution == b.resolution
}

/// Whether two views draw the same RGB pixels (their depth and segmentation outputs aside).
fn same_pixels(a: &View, b: &View) -> bool {
    Arc::ptr_eq(&a.scene, &b.scene) && a.camera == b.camera && a.poses == b.poses && a.resolution == b.resolution
}

/// An episode's last rendered observation: its views and their images. A step that leaves
/// what the views show unchanged (a rejected motion, a fetch with nothing in reach, a release
/// with nothing held: about a third of a random agent's steps) answers these images again
/// instead of rendering them anew; they are the pixels a new render would give, as the views
/// are equal. Cheap to clone; shared between the episode and the steps rendering for it.
#[derive(Clone, Default)]
struct FrameCache(Arc<std::sync::Mutex<Option<Frames>>>);

/// Views with their rendered images, in the same order.
struct Frames {
    views: Vec<View>,
    outputs: Vec<ViewOutput>,
}

impl FrameCache {
    /// The images of `views` if they are the last ones stored.
    fn lookup(&self, views: &[View]) -> Option<Vec<ViewOutput>> {
        let cached = self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        match &*cached {
            Some(frames)
                if frames.views.len() == views.len()
                    && frames.views.iter().zip(views).all(|(a, b)| same_view(a, b)) =>
            {
                Some(frames.outputs.clone())
            }
            _ => None,
        }
    }

    /// The images kept if their views pass `test`.
    fn lookup_where(&self, test: impl FnOnce(&[View]) -> bool) -> Option<Vec<ViewOutput>> {
        let cached = self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        cached.as_ref().filter(|frames| test(&frames.views)).map(|frames| frames.outputs.clone())
    }

    /// Keeps `outputs` as the images of `views` (replacing what was kept).
    fn store(&self, views: Vec<View>, outputs: &[ViewOutput]) {
        *self.0.lock().unwrap_or_else(std::sync::PoisonError::into_inner) =
            Some(Frames { views, outputs: outputs.to_vec() });
    }
}
