//! An OpenGL 4.3 core context with no window: EGL's surfaceless platform
//! (Mesa's llvmpipe on a machine without a GPU), libEGL loaded at run time so
//! the binary starts without it. Rendering goes to our own framebuffer
//! object, so the context needs no surface at all. 4.3 for the storage
//! buffers and early fragment tests of the atomic sample counters (Mesa's
//! llvmpipe gives 4.5).

use khronos_egl as egl;

/// `EGL_PLATFORM_SURFACELESS_MESA` (EGL_MESA_platform_surfaceless).
const PLATFORM_SURFACELESS_MESA: egl::Enum = 0x31DD;

/// A current GL context; dropping it releases the EGL objects.
pub struct GlContext {
    pub gl: glow::Context,
    egl: egl::DynamicInstance<egl::EGL1_5>,
    display: egl::Display,
    context: egl::Context,
    /// "vendor / renderer / version", for reports.
    pub renderer: String,
}

impl GlContext {
    /// Makes the context current on this thread. The error says what is
    /// missing (libEGL, the surfaceless platform, a GL 4.3 core config).
    pub fn new() -> Result<GlContext, String> {
        // SAFETY: loading libEGL runs its initialisers; it is the system's
        // EGL library, loaded once per context.
        let egl = unsafe { egl::DynamicInstance::<egl::EGL1_5>::load_required() }.map_err(|e| {
            format!(
                "cannot load libEGL ({e}); install libegl1 libegl-mesa0 libgl1-mesa-dri \
                 (Debian/Ubuntu) or a GPU driver's EGL"
            )
        })?;
        // SAFETY: the surfaceless platform takes no native display.
        let display = unsafe {
            egl.get_platform_display(
                PLATFORM_SURFACELESS_MESA,
                egl::DEFAULT_DISPLAY,
                &[egl::ATTRIB_NONE],
            )
        }
        .map_err(|e| format!("EGL surfaceless display unavailable: {e}"))?;
        egl.initialize(display)
            .map_err(|e| format!("eglInitialize failed: {e}"))?;
        let config = egl
            .choose_first_config(
                display,
                &[
                    egl::SURFACE_TYPE,
                    egl::PBUFFER_BIT,
                    egl::RENDERABLE_TYPE,
                    egl::OPENGL_BIT,
                    egl::NONE,
                ],
            )
            .map_err(|e| format!("eglChooseConfig failed: {e}"))?
            .ok_or("no EGL config with PBUFFER_BIT and desktop OpenGL")?;
        egl.bind_api(egl::OPENGL_API)
            .map_err(|e| format!("eglBindAPI(OPENGL) failed: {e}"))?;
        let context = egl
            .create_context(
                display,
                config,
                None,
                &[
                    egl::CONTEXT_MAJOR_VERSION,
                    4,
                    egl::CONTEXT_MINOR_VERSION,
                    3,
                    egl::CONTEXT_OPENGL_PROFILE_MASK,
                    egl::CONTEXT_OPENGL_CORE_PROFILE_BIT,
                    egl::NONE,
                ],
            )
            .map_err(|e| format!("cannot create an OpenGL 4.3 core context (storage buffers and atomics for the sample counters): {e}"))?;
        egl.make_current(display, None, None, Some(context))
            .map_err(|e| format!("eglMakeCurrent failed: {e}"))?;
        // SAFETY: the context is current on this thread; the loader returns
        // entry points of that context's library.
        let gl = unsafe {
            glow::Context::from_loader_function(|name| {
                egl.get_proc_address(name)
                    .map_or(std::ptr::null(), |f| f as *const _)
            })
        };
        use glow::HasContext;
        // SAFETY: plain queries on the current context.
        let renderer = unsafe {
            format!(
                "{} / {} / {}",
                gl.get_parameter_string(glow::VENDOR),
                gl.get_parameter_string(glow::RENDERER),
                gl.get_parameter_string(glow::VERSION)
            )
        };
        Ok(GlContext {
            gl,
            egl,
            display,
            context,
            renderer,
        })
    }
}

impl Drop for GlContext {
    fn drop(&mut self) {
        let _ = self.egl.make_current(self.display, None, None, None);
        let _ = self.egl.destroy_context(self.display, self.context);
    }
}
