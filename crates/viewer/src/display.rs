//! Getting an RGBA8 image onto the screen: a wgpu texture on the shared device, registered
//! with egui's renderer (written with `Queue::write_texture`), or an egui-managed texture
//! when there is no wgpu render state.

use eframe::egui;
use eframe::egui_wgpu::RenderState;
use eframe::wgpu;

/// One on-screen image that is replaced as a whole when it changes.
#[derive(Default)]
pub struct Display {
    native: Option<(wgpu::Texture, egui::TextureId)>,
    managed: Option<egui::TextureHandle>,
    size: [u32; 2],
}

impl Display {
    /// The texture to draw, once an image was set.
    pub fn id(&self) -> Option<egui::TextureId> {
        self.native
            .as_ref()
            .map(|(_, id)| *id)
            .or_else(|| self.managed.as_ref().map(egui::TextureHandle::id))
    }

    /// The current image's size in pixels.
    pub fn size(&self) -> [u32; 2] {
        self.size
    }

    /// Replaces the image with `rgba` (`width * height * 4` bytes, row-major, gamma-encoded
    /// sRGB like egui's own colours). Wrong sizes are ignored.
    pub fn set(
        &mut self,
        ctx: &egui::Context,
        render_state: Option<&RenderState>,
        label: &str,
        [width, height]: [u32; 2],
        rgba: &[u8],
    ) {
        if width == 0 || height == 0 || rgba.len() != width as usize * height as usize * 4 {
            return;
        }
        match render_state {
            Some(rs) => self.set_native(rs, label, [width, height], rgba),
            None => {
                let image = egui::ColorImage::from_rgba_unmultiplied(
                    [width as usize, height as usize],
                    rgba,
                );
                match &mut self.managed {
                    Some(h) => h.set(image, egui::TextureOptions::LINEAR),
                    None => {
                        self.managed =
                            Some(ctx.load_texture(label, image, egui::TextureOptions::LINEAR))
                    }
                }
            }
        }
        self.size = [width, height];
    }

    fn set_native(&mut self, rs: &RenderState, label: &str, [w, h]: [u32; 2], rgba: &[u8]) {
        let size = wgpu::Extent3d {
            width: w,
            height: h,
            depth_or_array_layers: 1,
        };
        let resized = self
            .native
            .as_ref()
            .is_none_or(|(t, _)| t.width() != w || t.height() != h);
        if resized {
            let texture = rs.device.create_texture(&wgpu::TextureDescriptor {
                label: Some(label),
                size,
                mip_level_count: 1,
                sample_count: 1,
                dimension: wgpu::TextureDimension::D2,
                // egui-wgpu expects gamma-space RGBA8 in user textures.
                format: wgpu::TextureFormat::Rgba8Unorm,
                usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                view_formats: &[],
            });
            let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
            let mut renderer = rs.renderer.write();
            let id = match self.native.take() {
                Some((old, id)) => {
                    renderer.update_egui_texture_from_wgpu_texture(
                        &rs.device,
                        &view,
                        wgpu::FilterMode::Linear,
                        id,
                    );
                    old.destroy();
                    id
                }
                None => {
                    renderer.register_native_texture(&rs.device, &view, wgpu::FilterMode::Linear)
                }
            };
            self.native = Some((texture, id));
        }
        if let Some((texture, _)) = &self.native {
            rs.queue.write_texture(
                wgpu::TexelCopyTextureInfo {
                    texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d::ZERO,
                    aspect: wgpu::TextureAspect::All,
                },
                rgba,
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(4 * w),
                    rows_per_image: Some(h),
                },
                size,
            );
        }
    }
}
