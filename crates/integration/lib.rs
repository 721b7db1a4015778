//! Holder for the workspace-level tests in the repository's `tests/` folder (for example
//! `tests/conformance.rs`), and the headless-Chromium driver the browser checks share
//! ([`browser`]).

pub mod browser {
    //! A page served on 127.0.0.1 (a secure context, as WebGPU wants) to headless Chromium
    //! on SwiftShader's WebGPU; the page reports by `POST /result` (or `POST /error`).

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
            _ => "application/octet-stream",
        }
    }

    /// Serves `files(path)` for each GET and sends each POST to the returned channel.
    fn serve(
        files: impl Fn(&str) -> Option<Vec<u8>> + Send + Sync + 'static,
    ) -> std::io::Result<(u16, mpsc::Receiver<Report>)> {
        let listener = TcpListener::bind("127.0.0.1:0")?;
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
                    let path = request.split(' ').nth(1).unwrap_or("/").to_string();
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

    /// Opens `/` of a server for `files` in headless `chromium` with WebGPU on SwiftShader
    /// and returns the page's first report, or an error after `timeout` (the browser is
    /// closed either way).
    pub fn run_page(
        chromium: &str,
        files: impl Fn(&str) -> Option<Vec<u8>> + Send + Sync + 'static,
        timeout: Duration,
    ) -> Result<Report, String> {
        let (port, reports) = serve(files).map_err(|e| format!("serving the page: {e}"))?;
        let profile = std::env::temp_dir().join(format!("bvhtrace-chromium-{port}"));
        // The browser's console, for a page that fails: `BVHTRACE_CHROMIUM_LOG=FILE`.
        let log =
            std::env::var_os("BVHTRACE_CHROMIUM_LOG").and_then(|f| std::fs::File::create(f).ok());
        let mut child = Command::new(chromium)
            .args([
                "--headless=new",
                "--no-sandbox",
                "--enable-unsafe-webgpu",
                "--use-webgpu-adapter=swiftshader",
                "--enable-unsafe-swiftshader",
            ])
            .arg(format!("--user-data-dir={}", profile.display()))
            .arg(format!("http://127.0.0.1:{port}/"))
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
