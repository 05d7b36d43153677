//! The device's own clock: the two timestamp queries a batch carries when its renderer times the
//! device (the start of its first pass and the end of its last), how they are read back, and the
//! check at a renderer's creation that they work on its device.

use std::time::Duration;

use super::formats::COLOUR_FORMAT;

/// The bytes after the used pages of the readback buffer that hold a batch's two timestamps
/// (in the device's ticks).
pub(super) const TIMESTAMP_BYTES: u64 = 2 * wgpu::QUERY_SIZE as u64;

/// A batch's two timestamp queries and the buffer they are resolved into before they are copied
/// behind the batch's pages in the readback buffer (a resolve needs a 256-byte aligned offset,
/// the pages' ends only have 4).
pub(super) struct StampQueries {
    pub(super) set: wgpu::QuerySet,
    pub(super) resolved: wgpu::Buffer,
}

impl StampQueries {
    pub(super) fn new(device: &wgpu::Device) -> Self {
        let set = device.create_query_set(&wgpu::QuerySetDescriptor {
            label: Some("esrp-render batch timestamps"),
            ty: wgpu::QueryType::Timestamp,
            count: 2,
        });
        let resolved = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("esrp-render batch timestamps"),
            size: TIMESTAMP_BYTES,
            usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        });
        Self { set, resolved }
    }
}

/// The time between the two timestamps at the start of `stamps` (little-endian ticks of
/// `period` nanoseconds), or `None` if they are not in order (a device whose clock was reset,
/// or that wrote nothing).
pub(super) fn drawing_time(stamps: &[u8], period: f32) -> Option<Duration> {
    let tick = |i: usize| Some(u64::from_le_bytes(stamps.get(i * 8..i * 8 + 8)?.try_into().ok()?));
    let (start, end) = (tick(0)?, tick(1)?);
    (start != 0 && end >= start).then(|| Duration::from_secs_f64((end - start) as f64 * f64::from(period) * 1e-9))
}

/// Checks that timestamps work on `device` as batches use them: a render pass on a small target
/// writing both, resolved, copied into a mappable buffer and read back in order. A device that
/// fails it is not timed (a batch's error would fail its views), and says why.
pub(super) fn check_timestamps(device: &wgpu::Device, queue: &wgpu::Queue) -> Result<(), String> {
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let target = device.create_texture(&wgpu::TextureDescriptor {
        label: Some("esrp-render timestamp check"),
        size: wgpu::Extent3d { width: 64, height: 64, depth_or_array_layers: 1 },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: COLOUR_FORMAT,
        usage: wgpu::TextureUsages::RENDER_ATTACHMENT,
        view_formats: &[],
    });
    let view = target.create_view(&Default::default());
    let timestamps = StampQueries::new(device);
    let readback = device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("esrp-render timestamp check"),
        size: TIMESTAMP_BYTES,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder =
        device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("esrp-render timestamp check") });
    drop(encoder.begin_render_pass(&wgpu::RenderPassDescriptor {
        label: Some("esrp-render timestamp check"),
        color_attachments: &[Some(wgpu::RenderPassColorAttachment {
            view: &view,
            depth_slice: None,
            resolve_target: None,
            ops: wgpu::Operations { load: wgpu::LoadOp::Clear(wgpu::Color::BLACK), store: wgpu::StoreOp::Store },
        })],
        depth_stencil_attachment: None,
        timestamp_writes: Some(wgpu::RenderPassTimestampWrites {
            query_set: &timestamps.set,
            beginning_of_pass_write_index: Some(0),
            end_of_pass_write_index: Some(1),
        }),
        occlusion_query_set: None,
        multiview_mask: None,
    }));
    encoder.resolve_query_set(&timestamps.set, 0..2, &timestamps.resolved, 0);
    encoder.copy_buffer_to_buffer(&timestamps.resolved, 0, &readback, 0, TIMESTAMP_BYTES);
    let submission = queue.submit([encoder.finish()]);
    let (sender, mapped) = std::sync::mpsc::channel();
    readback.map_async(wgpu::MapMode::Read, .., move |result| {
        let _ = sender.send(result);
    });
    if let Some(error) = pollster::block_on(scope.pop()) {
        return Err(error.to_string());
    }
    device
        .poll(wgpu::PollType::Wait { submission_index: Some(submission), timeout: Some(Duration::from_secs(10)) })
        .map_err(|e| e.to_string())?;
    match mapped.recv_timeout(Duration::from_secs(10)) {
        Ok(Ok(())) => {}
        Ok(Err(e)) => return Err(format!("its buffer could not be read back: {e}")),
        Err(_) => return Err("its buffer was not read back within 10 s".into()),
    }
    let ticks: Vec<u8> = readback.get_mapped_range(..).map_err(|e| format!("{e:?}"))?.to_vec();
    readback.unmap();
    drawing_time(&ticks, queue.get_timestamp_period())
        .map(|_| ())
        .ok_or_else(|| format!("the device wrote timestamps out of order ({ticks:?})"))
}

#[cfg(test)]
mod tests {
    use super::drawing_time;

    #[test]
    fn the_drawing_time_is_the_ticks_between_the_stamps_in_the_period() {
        let stamps = |start: u64, end: u64| [start.to_le_bytes(), end.to_le_bytes()].concat();
        assert_eq!(drawing_time(&stamps(1_000, 3_500), 1.0), Some(std::time::Duration::from_nanos(2_500)));
        assert_eq!(drawing_time(&stamps(10, 20), 2.5), Some(std::time::Duration::from_nanos(25)));
        assert_eq!(drawing_time(&stamps(7, 7), 1.0), Some(std::time::Duration::ZERO));
        assert_eq!(drawing_time(&stamps(20, 10), 1.0), None, "out of order");
        assert_eq!(drawing_time(&stamps(0, 10), 1.0), None, "nothing written");
        assert_eq!(drawing_time(&stamps(1, 2)[..12], 1.0), None, "cut short");
    }
}
