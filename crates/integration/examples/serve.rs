//! Serves a folder on 127.0.0.1 for a browser: `web/serve.sh` runs it on web/dist.
//!
//! ```text
//! cargo run --release -p bvhtrace-integration --example serve -- DIR [PORT]
//! ```

use std::path::PathBuf;

use bvhtrace_integration::browser::{self, Report};

fn main() {
    let mut args = std::env::args().skip(1);
    let Some(dir) = args.next().map(PathBuf::from) else {
        eprintln!("usage: serve DIR [PORT]");
        std::process::exit(2);
    };
    let port = match args.next().map(|p| p.parse::<u16>()) {
        None => 8000,
        Some(Ok(p)) => p,
        Some(Err(e)) => {
            eprintln!("error: the port: {e}");
            std::process::exit(2);
        }
    };
    if !dir.join("index.html").is_file() {
        eprintln!(
            "error: {} has no index.html: run web/build.sh first",
            dir.display()
        );
        std::process::exit(1);
    }
    let (port, reports) = match browser::serve(port, browser::folder(dir.clone())) {
        Ok(served) => served,
        Err(e) => {
            eprintln!("error: serving on 127.0.0.1:{port}: {e}");
            std::process::exit(1);
        }
    };
    println!(
        "serving {} on http://127.0.0.1:{port}/ (index.html: the library; viewer.html: the viewer); Ctrl-C stops",
        dir.display()
    );
    // A page's reports (the browser test's pages post them), printed.
    for report in reports {
        match report {
            Report::Result(bytes) => println!("page result: {} bytes", bytes.len()),
            Report::Error(e) => println!("page error: {e}"),
        }
    }
}
