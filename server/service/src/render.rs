//! The render scheduler: dedicated threads share the renderers (`--render-devices`, each with
//! its own device and queue, every scene uploaded to each); each thread renders on one of them,
//! gathers the view requests of all episodes that arrived while it was busy, and renders them in
//! one batch.
//!
//! With more than one batch in flight per thread (`--render-pipeline`), a render thread only
//! gathers, encodes and submits; a readback thread beside it waits for the device, cuts the
//! images out and answers, so that the device draws one batch while the next is encoded and the
//! last is read back.
//!
//! The async side sends a [`RenderJob`] (the views of one request) down a channel and awaits
//! the reply; the runtime never blocks on rendering. Batching is automatic: the more episodes
//! step at once, the larger the batches.

use std::sync::Arc;
use std::sync::mpsc;
use std::time::Instant;

use esrp_core::{CompiledScene, EgoCamera, ObjectPose};
use esrp_render::{Camera, Outputs, Renderer, SceneHandle, TopDownFrame, ViewOutput, ViewRequest};
use tokio::sync::oneshot;

use crate::error::ServiceError;
use crate::metrics::{Metrics, Stages};

/// The render threads per renderer that `--render-threads 0` (auto) starts: one, on every backend,
/// as measured (docs/performance.md, issue 40). On a software renderer Mesa rasterises one scene
/// at a time per process, so a second thread only contends (slower on the 2-core VM); on an
/// NVIDIA H200 through Vulkan, 2, 4 and 8 threads sharing its device were each slower than one,
/// the threads queueing behind each other for the one device. A machine scales with several
/// server processes instead (docs/server.md).
pub const AUTO_RENDER_THREADS: usize = 1;

/// The render devices `--render-devices 0` (auto) opens: one.
pub const AUTO_RENDER_DEVICES: usize = 1;

/// The batches in flight per render thread that `--render-pipeline 0` (auto) allows: one (the
/// thread submits a batch and reads it back before it gathers the next), as measured on the
/// 2-core VM's software renderers (docs/performance.md, issue 40); a GPU's figure is to be
/// measured with `scripts/gpu-bench.sh`.
pub const AUTO_RENDER_PIPELINE: usize = 1;

/// A scene uploaded to every renderer of the scheduler: its handle on each device, in the
/// renderers' order.
#[derive(Debug)]
pub struct DeviceScenes(Vec<Arc<SceneHandle>>);

impl DeviceScenes {
    /// The handle on renderer `device`.
    fn on(&self, device: usize) -> &SceneHandle {
        &self.0[device % self.0.len()]
    }

    /// The top-down view's frame at `resolution` (the same on every device).
    pub fn top_down_frame(&self, resolution: u32) -> TopDownFrame {
        self.0[0].top_down_frame(resolution)
    }
}

/// One view to render, owning its inputs.
#[derive(Clone, Debug)]
pub struct View {
    /// The scene.
    pub scene: Arc<DeviceScenes>,
    /// Egocentric or top-down.
    pub camera: Camera,
    /// Poses of the movable objects.
    pub poses: Vec<ObjectPose>,
    /// Extra outputs.
    pub outputs: Outputs,
    /// Square side in pixels.
    pub resolution: u32,
}

impl View {
    /// The egocentric view at `camera`.
    pub fn ego(
        scene: &Arc<DeviceScenes>,
        camera: EgoCamera,
        poses: &[ObjectPose],
        outputs: Outputs,
        resolution: u32,
    ) -> Self {
        Self { scene: scene.clone(), camera: Camera::Ego(camera), poses: poses.to_vec(), outputs, resolution }
    }

    /// The top-down view with the objects at `poses`.
    pub fn top_down(scene: &Arc<DeviceScenes>, poses: &[ObjectPose], resolution: u32) -> Self {
        Self { scene: scene.clone(), camera: Camera::TopDown, poses: poses.to_vec(), outputs: Outputs::RGB, resolution }
    }
}

struct RenderJob {
    views: Vec<View>,
    reply: oneshot::Sender<Result<Vec<ViewOutput>, String>>,
    /// When it was sent (the `render_queue` stage ends when a render thread takes it).
    sent: Instant,
}

/// What the render threads receive.
enum Message {
    /// Views to render.
    Job(RenderJob),
    /// Finish the jobs sent before this one, then end (one per thread, from
    /// [`RenderScheduler::stop`]).
    Stop,
}

/// Handle to the render threads. Cheap to clone.
#[derive(Clone)]
pub struct RenderScheduler {
    /// At least one.
    renderers: Arc<[Arc<Renderer>]>,
    jobs: mpsc::Sender<Message>,
    /// The render threads, until [`RenderScheduler::stop`] joins them.
    threads: Arc<std::sync::Mutex<Vec<std::thread::JoinHandle<()>>>>,
}

impl RenderScheduler {
    /// Starts `threads` render threads around `renderers` (at least one each: thread i renders
    /// on renderer i modulo their number, and there are at least as many threads as renderers),
    /// each with up to `in_flight` batches submitted and not yet read back (at least one; more
    /// than one starts a readback thread beside each render thread).
    pub fn start(renderers: Vec<Renderer>, metrics: Arc<Metrics>, threads: usize, in_flight: usize) -> Self {
        assert!(!renderers.is_empty(), "a render scheduler needs a renderer");
        let count = threads.max(renderers.len());
        let renderers: Arc<[Arc<Renderer>]> = renderers.into_iter().map(Arc::new).collect();
        let (jobs, receiver) = mpsc::channel::<Message>();
        let receiver = Arc::new(std::sync::Mutex::new(receiver));
        let mut threads = Vec::with_capacity(count);
        for i in 0..count {
            let device = i % renderers.len();
            let (renderer, receiver, metrics) = (renderers[device].clone(), receiver.clone(), metrics.clone());
            match std::thread::Builder::new()
                .name(format!("esrp-render-{i}"))
                .spawn(move || render_loop(&renderer, device, i, &receiver, &metrics, in_flight))
            {
                Ok(thread) => threads.push(thread),
                Err(e) => tracing::error!("cannot start a render thread: {e}"),
            }
        }
        metrics.render_threads.set(threads.len() as i64);
        metrics.render_pipeline.set(in_flight.max(1) as i64);
        metrics.render_timestamps.set(i64::from(renderers.iter().all(|r| r.times_device())));
        Self { renderers, jobs, threads: Arc::new(std::sync::Mutex::new(threads)) }
    }

    /// Renders what was submitted before this call, then ends the render threads and waits for
    /// them (blocking: call it off the async runtime). Later submissions fail with "the render
    /// thread has stopped". Idempotent.
    ///
    /// The server calls it on shutdown, before `main` returns: a render thread still running
    /// when the process exits would drop its share of the renderer (the last one, once the
    /// episodes are gone) while the main thread runs the exit handlers, and with OpenGL that
    /// tore the driver's state down twice at once (heap corruption, SIGSEGV/SIGABRT).
    pub fn stop(&self) {
        let threads = match self.threads.lock() {
            Ok(mut threads) => std::mem::take(&mut *threads),
            Err(poisoned) => std::mem::take(&mut *poisoned.into_inner()),
        };
        for _ in &threads {
            let _ = self.jobs.send(Message::Stop);
        }
        for thread in threads {
            if thread.join().is_err() {
                tracing::error!("a render thread panicked");
            }
        }
    }

    /// The first renderer (adapter information, limits: the same on every device).
    pub fn renderer(&self) -> &Arc<Renderer> {
        &self.renderers[0]
    }

    /// Uploads a scene's geometry to every renderer (on a blocking thread).
    pub async fn upload(&self, scene: Arc<CompiledScene>) -> Result<Arc<DeviceScenes>, ServiceError> {
        let renderers = self.renderers.clone();
        let handles = tokio::task::spawn_blocking(move || {
            renderers.iter().map(|renderer| renderer.upload_scene(&scene)).collect::<Result<Vec<_>, _>>()
        })
        .await
        .map_err(|e| ServiceError::Internal(e.to_string()))?
        .map_err(ServiceError::from)?;
        Ok(Arc::new(DeviceScenes(handles)))
    }

    /// Renders `views`, batched with whatever other episodes asked for meanwhile.
    pub async fn render(&self, views: Vec<View>) -> Result<Vec<ViewOutput>, ServiceError> {
        self.submit(views).wait().await
    }

    /// Hands `views` to the render thread now; the ticket waits for them. The views are
    /// snapshots: the episodes they show may move on meanwhile.
    pub fn submit(&self, views: Vec<View>) -> RenderTicket {
        if views.is_empty() {
            return RenderTicket::nothing();
        }
        let (reply, answer) = oneshot::channel();
        match self.jobs.send(Message::Job(RenderJob { views, reply, sent: Instant::now() })) {
            Ok(()) => RenderTicket(Ticket::Waiting(answer)),
            Err(_) => RenderTicket(Ticket::Done(Err(ServiceError::Render("the render thread has stopped".into())))),
        }
    }
}

/// Views handed to the render thread ([`RenderScheduler::submit`]).
pub struct RenderTicket(Ticket);

enum Ticket {
    Waiting(oneshot::Receiver<Result<Vec<ViewOutput>, String>>),
    Done(Result<Vec<ViewOutput>, ServiceError>),
}

impl RenderTicket {
    /// A ticket for no views.
    pub fn nothing() -> Self {
        RenderTicket(Ticket::Done(Ok(Vec::new())))
    }

    /// The rendered views, in the order they were submitted.
    pub async fn wait(self) -> Result<Vec<ViewOutput>, ServiceError> {
        match self.0 {
            Ticket::Done(result) => result,
            Ticket::Waiting(answer) => answer
                .await
                .map_err(|_| ServiceError::Render("the render thread dropped the request".into()))?
                .map_err(ServiceError::Render),
        }
    }
}

/// What a render thread hands its readback thread: a submitted batch, the jobs whose views it
/// holds, and when it was taken from the queue.
type Submitted = (esrp_render::SubmittedBatch, Vec<RenderJob>, Instant);

fn render_loop(
    renderer: &Arc<Renderer>,
    device: usize,
    index: usize,
    receiver: &std::sync::Mutex<mpsc::Receiver<Message>>,
    metrics: &Arc<Metrics>,
    in_flight: usize,
) {
    // More than one batch in flight: a readback thread finishes them in order while this one
    // submits the next. The channel holds `in_flight - 2`: one is being read back and one more
    // waits here, submitted, to be handed over.
    let readback = (in_flight > 1).then(|| {
        let (sender, batches) = mpsc::sync_channel::<Submitted>(in_flight - 2);
        let (renderer, metrics) = (renderer.clone(), metrics.clone());
        std::thread::Builder::new()
            .name(format!("esrp-readback-{index}"))
            .spawn(move || {
                for (batch, jobs, started) in batches {
                    let result = renderer.finish_batch(batch);
                    metrics.batch_seconds.observe(started.elapsed().as_secs_f64());
                    answer(jobs, result, &metrics);
                }
            })
            .map(|thread| (sender, thread))
            .map_err(|e| tracing::error!("cannot start a readback thread, rendering one batch at a time: {e}"))
            .ok()
    });
    let (sender, readback_thread) = readback.flatten().unzip();
    loop {
        // Gather under the lock, render without it: while one thread renders, the other
        // gathers the next batch and submits it as soon as it can.
        let Ok(receiver) = receiver.lock() else { break };
        let first = match receiver.recv() {
            Ok(Message::Job(job)) => job,
            Ok(Message::Stop) | Err(_) => break,
        };
        // Gather the jobs already waiting, about one submission's worth (the renderer takes
        // any number of views and draws them in chunks of its own).
        let mut jobs = vec![first];
        let mut count = jobs[0].views.len();
        let mut stop = false;
        while count < esrp_render::CHUNK_VIEWS {
            match receiver.try_recv() {
                Ok(Message::Job(job)) => {
                    count += job.views.len();
                    jobs.push(job);
                }
                Ok(Message::Stop) => {
                    stop = true;
                    break;
                }
                Err(_) => break,
            }
        }
        drop(receiver);
        let taken = Instant::now();
        for job in &jobs {
            Stages::add(&metrics.stages.render_queue, taken.saturating_duration_since(job.sent));
        }
        metrics.batch_views.observe(count as f64);
        match &sender {
            None => {
                let result = renderer.render_batch_timed(&requests(&jobs, device));
                metrics.batch_seconds.observe(taken.elapsed().as_secs_f64());
                answer(jobs, result, metrics);
            }
            Some(sender) => {
                let submitted = renderer.submit_batch(&requests(&jobs, device));
                match submitted {
                    Ok(batch) => {
                        if let Err(mpsc::SendError((_, jobs, _))) = sender.send((batch, jobs, taken)) {
                            answer(
                                jobs,
                                Err(esrp_render::RenderError::Readback {
                                    reason: "the readback thread has stopped".into(),
                                }),
                                metrics,
                            );
                        }
                    }
                    Err(e) => answer(jobs, Err(e), metrics),
                }
            }
        }
        if stop {
            break;
        }
    }
    // The batches still in flight are read back and answered before the thread ends.
    drop(sender);
    if let Some(thread) = readback_thread
        && thread.join().is_err()
    {
        tracing::error!("a readback thread panicked");
    }
}

/// The renderer's requests for every view of `jobs`, in order, on renderer `device`.
fn requests(jobs: &[RenderJob], device: usize) -> Vec<ViewRequest<'_>> {
    jobs.iter()
        .flat_map(|job| job.views.iter())
        .map(|v| {
            ViewRequest::new(v.scene.on(device), v.camera, &v.poses)
                .with_outputs(v.outputs)
                .with_resolution(v.resolution)
        })
        .collect()
}

/// Adds a rendered batch's stages to the metrics and answers each job with its views, or every
/// job with the batch's error.
fn answer(
    jobs: Vec<RenderJob>,
    result: Result<(Vec<ViewOutput>, esrp_render::RenderTimings), esrp_render::RenderError>,
    metrics: &Metrics,
) {
    match result {
        Ok((outputs, timings)) => {
            Stages::add(&metrics.stages.render_encode, timings.encode);
            Stages::add(&metrics.stages.render_submit, timings.submit);
            Stages::add(&metrics.stages.render_device, timings.device);
            if let Some(drawing) = timings.gpu {
                Stages::add(&metrics.render_gpu_seconds, drawing);
            }
            Stages::add(&metrics.stages.render_extract, timings.extract);
            metrics.atlases_created.inc_by(u64::from(timings.new_atlases));
            let mut outputs = outputs.into_iter();
            for job in jobs {
                let mine: Vec<ViewOutput> = outputs.by_ref().take(job.views.len()).collect();
                let _ = job.reply.send(Ok(mine));
            }
        }
        Err(e) => {
            let message = e.to_string();
            for job in jobs {
                let _ = job.reply.send(Err(message.clone()));
            }
        }
    }
}
