//! The site map in CI: `rangegp-eval sitemap --quick` (a 340 m drive with the daemon in process)
//! must keep memory with the radius and bring the start area back from disk exactly. The full
//! form drives 1 km (docs/EVALUATION.md "Site map").

use rangegp_lab::eval::sitemap::{run_sitemap, SitemapOptions};
use rangegp_lab::heap;

/// Counted, for the memory bar (`rangegp_lab::heap`).
#[global_allocator]
static HEAP: heap::Counting = heap::counting();

#[test]
fn a_drive_pages_tiles_out_and_back_exactly_with_bounded_memory() -> anyhow::Result<()> {
    heap::register(&HEAP);
    let report = run_sitemap(&SitemapOptions { quick: true, seed: 0 })?;
    assert!(report.failures.is_empty(), "{:?}\n{report:?}", report.failures);
    assert!(report.paged_out > 0 && report.revisit_points >= 20, "{report:?}");
    assert!(report.held_warm_mb > 50.0, "the heap is counted: {report:?}");
    Ok(())
}
