//! The committed header is the one cbindgen generates from the sources (the build script writes
//! it to OUT_DIR): a changed signature without a regenerated header fails here.

#[test]
fn the_committed_header_is_the_generated_one() {
    let generated = include_str!(concat!(env!("OUT_DIR"), "/rangegp.h"));
    let committed = include_str!("../include/rangegp.h");
    assert!(
        generated == committed,
        "capi/include/rangegp.h is stale: copy {}/rangegp.h over it",
        env!("OUT_DIR")
    );
}
