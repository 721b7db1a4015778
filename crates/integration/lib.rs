//! Holder for the workspace-level tests in the repository's `tests/` folder (for example
//! `tests/conformance.rs`), and the headless-Chromium driver the browser checks share
//! ([`browser`]).

pub mod browser {
    //! A page served on 127.0.0.1 (a secure context, as WebGPU wants) to headless Chromium
    //! ([`WebGpu`]: on SwiftShader, or on the system's Vulkan driver); the page reports by
    //! `POST /result` (or `POST /error`).

    use std::io::{BufRead, BufReader, Read, Write};
    use std::net::TcpListener;
    use std::process::{Command, Stdio};
    use std::sync::mpsc;
    use std::time::Duration;

    /// What a page reported.
    #[derive(Debug)]
    pub enum Report {
        /// The body of `POST /result`.
        Result(Vec<u8>),
        /// The body of `POST /error`: a message from the page.
        Error(String),
    }

    /// Which WebGPU implementation Chromium's Dawn runs on.
    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    pub enum WebGpu {
        /// SwiftShader, Chromium's own CPU Vulkan: compute only here, since headless
        /// Chromium loses the device when a page presents a WebGPU canvas on it.
        SwiftShader,
        /// The system's Vulkan driver (lavapipe on a machine without a GPU), with ANGLE on
        /// Vulkan for the compositor: canvases present, so the viewer's page runs.
        Vulkan,
    }

    impl WebGpu {
        /// Chromium's flags for it.
        pub fn flags(self) -> &'static [&'static str] {
            match self {
                WebGpu::SwiftShader => &[
                    "--use-webgpu-adapter=swiftshader",
                    "--enable-unsafe-swiftshader",
                ],
                WebGpu::Vulkan => &[
                    "--enable-features=Vulkan,DefaultANGLEVulkan,VulkanFromANGLE",
                    "--use-angle=vulkan",
                    "--use-vulkan=native",
                ],
            }
        }
    }

    /// The triangles of the scene the browser checks trace: `spec`, or `bunny_69k` from
    /// the shared scenes when that folder is there, else the builtin icosphere (said on
    /// stdout); with the spec that was loaded.
    pub fn scene_or_bunny(
        spec: Option<String>,
    ) -> Result<(String, Vec<bvhtrace_core::Triangle>), Box<dyn std::error::Error>> {
        use bvhtrace_scene::shared_scenes_dir;
        let spec = match (spec, shared_scenes_dir()) {
            (Some(spec), _) => spec,
            (None, Some(dir)) => dir.join("glb/bunny_69k.glb").to_string_lossy().into_owned(),
            (None, None) => {
                println!("no shared scenes folder: using builtin:icosphere:6 instead of bunny_69k");
                "builtin:icosphere:6".to_string()
            }
        };
        let load = bvhtrace_scene::LoadOptions::with_meshes(shared_scenes_dir());
        let tris = bvhtrace_scene::load_with(&spec, &load)?
            .flatten()
            .triangles()?;
        Ok((spec, tris))
    }

    /// The Chromium binary: `$BVHTRACE_CHROMIUM`, else `chromium`; `None` when it does not
    /// run.
    pub fn chromium() -> Option<String> {
        let name = std::env::var("BVHTRACE_CHROMIUM").unwrap_or_else(|_| "chromium".into());
        Command::new(&name)
            .arg("--version")
            .output()
            .ok()
            .map(|_| name)
    }

    /// The content type of a served file, by its extension.
    fn content_type(path: &str) -> &'static str {
        let name = path.rsplit('/').next().unwrap_or_default();
        match name.rsplit_once('.').map(|(_, ext)| ext) {
            Some("wasm") => "application/wasm",
            Some("js") => "text/javascript",
            Some("html") | None => "text/html",
            Some("png") => "image/png",
            Some("glb") => "model/gltf-binary",
            Some("gltf") => "model/gltf+json",
            _ => "application/octet-stream",
        }
    }

    /// Serves `files(path)` (the path without its query) for each GET on 127.0.0.1:`port`
    /// (0: any free port), and sends each POST to the returned channel.
    pub fn serve(
        port: u16,
        files: impl Fn(&str) -> Option<Vec<u8>> + Send + Sync + 'static,
    ) -> std::io::Result<(u16, mpsc::Receiver<Report>)> {
        let listener = TcpListener::bind(("127.0.0.1", port))?;
        let port = listener.local_addr()?.port();
        let (tx, rx) = mpsc::channel();
        let files = std::sync::Arc::new(files);
        std::thread::spawn(move || {
            // A thread per connection: a browser opens connections it sends nothing on.
            for stream in listener.incoming().flatten() {
                let (files, tx) = (files.clone(), tx.clone());
                std::thread::spawn(move || {
                    let mut reader = BufReader::new(&stream);
                    let (mut request, mut line, mut length) = (String::new(), String::new(), 0);
                    let _ = reader.read_line(&mut request);
                    while reader.read_line(&mut line).is_ok_and(|n| n > 2) {
                        if let Some(v) = line.to_ascii_lowercase().strip_prefix("content-length:") {
                            length = v.trim().parse().unwrap_or(0);
                        }
                        line.clear();
                    }
                    let mut body = vec![0; length];
                    let _ = reader.read_exact(&mut body);
                    let target = request.split(' ').nth(1).unwrap_or("/");
                    let path = target.split('?').next().unwrap_or("/").to_string();
                    let (status, kind, reply) = if request.starts_with("POST /log") {
                        // Progress from the page, to the terminal.
                        eprintln!("page: {}", String::from_utf8_lossy(&body));
                        ("200 OK", "text/plain", Vec::new())
                    } else if request.starts_with("POST") {
                        let _ = tx.send(match path.as_str() {
                            "/result" => Report::Result(body),
                            _ => Report::Error(String::from_utf8_lossy(&body).into_owned()),
                        });
                        ("200 OK", "text/plain", Vec::new())
                    } else {
                        match files(&path) {
                            Some(bytes) => ("200 OK", content_type(&path), bytes),
                            None => ("404 Not Found", "text/plain", Vec::new()),
                        }
                    };
                    let head = format!(
                        "HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {}\r\n\
                     Connection: close\r\n\r\n",
                        reply.len()
                    );
                    let mut s = &stream;
                    let _ = s
                        .write_all(head.as_bytes())
                        .and_then(|_| s.write_all(&reply));
                });
            }
        });
        Ok((port, rx))
    }

    /// The files of folder `dir` by URL path (`/` is `index.html`); nothing outside it.
    pub fn folder(dir: std::path::PathBuf) -> impl Fn(&str) -> Option<Vec<u8>> + Send + Sync {
        move |path: &str| {
            let rel = path.trim_start_matches('/');
            let rel = if rel.is_empty() { "index.html" } else { rel };
            if rel.split('/').any(|part| part == ".." || part.is_empty()) {
                return None;
            }
            std::fs::read(dir.join(rel)).ok()
        }
    }

    /// Opens `path` (with its query) of a server for `files` in headless `chromium` with
    /// WebGPU on SwiftShader and returns the page's first report, or an error after
    /// `timeout` (the browser is closed either way).
    pub fn run_page(
        chromium: &str,
        files: impl Fn(&str) -> Option<Vec<u8>> + Send + Sync + 'static,
        path: &str,
        timeout: Duration,
    ) -> Result<Report, String> {
        open_page(
            chromium,
            WebGpu::SwiftShader,
            files,
            path,
            (800, 600),
            timeout,
        )
    }

    /// [`run_page`] in a window of `size` pixels, with WebGPU on `webgpu`.
    pub fn open_page(
        chromium: &str,
        webgpu: WebGpu,
        files: impl Fn(&str) -> Option<Vec<u8>> + Send + Sync + 'static,
        path: &str,
        size: (u32, u32),
        timeout: Duration,
    ) -> Result<Report, String> {
        let (port, reports) = serve(0, files).map_err(|e| format!("serving the page: {e}"))?;
        let profile = std::env::temp_dir().join(format!("bvhtrace-chromium-{port}"));
        // The browser's console, for a page that fails: `BVHTRACE_CHROMIUM_LOG=FILE`.
        let log =
            std::env::var_os("BVHTRACE_CHROMIUM_LOG").and_then(|f| std::fs::File::create(f).ok());
        let mut command = Command::new(chromium);
        if webgpu == WebGpu::SwiftShader {
            // SwiftShader is a Vulkan driver of Chromium's own, which the loader finds only
            // when it is not told to load others alone (CI points it at Mesa 25).
            command
                .env_remove("VK_ICD_FILENAMES")
                .env_remove("VK_DRIVER_FILES");
        }
        let mut child = command
            .args(["--headless=new", "--no-sandbox", "--enable-unsafe-webgpu"])
            .args(webgpu.flags())
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg(format!("--window-size={},{}", size.0, size.1))
            .arg(format!("http://127.0.0.1:{port}{path}"))
            .args(
                log.iter()
                    .flat_map(|_| ["--enable-logging=stderr", "--v=1"]),
            )
            .stdout(Stdio::null())
            .stderr(match log {
                Some(f) => Stdio::from(f),
                None => Stdio::null(),
            })
            .spawn()
            .map_err(|e| format!("starting {chromium}: {e}"))?;
        let report = reports.recv_timeout(timeout);
        let _ = child.kill();
        let _ = child.wait();
        let _ = std::fs::remove_dir_all(&profile);
        report.map_err(|_| format!("the page reported nothing within {} s", timeout.as_secs()))
    }
}

/// README.md's library example, compiled and run as this crate's doctest.
#[cfg(doctest)]
#[doc = include_str!("../../README.md")]
pub struct ReadmeExample;
