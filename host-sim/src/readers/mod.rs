//! The readers: structure-from-motion models into [`Scene`]s (COLMAP,
//! BAL, Bundler, OpenSfM, on the strict low-level parsing of [`parse`]), and query
//! keypoints from the files a user has ([`keypoints`]). [`SceneSource`] names a model on the
//! command line and reads it with its reader.

pub mod bal;
pub mod bundler;
pub mod colmap;
pub mod keypoints;
pub mod opensfm;
pub mod parse;

use std::path::PathBuf;

use crate::scene::{Scene, RANK_BLOCK};

/// Where a scene comes from, as named on the command line.
#[derive(Debug, Clone, PartialEq)]
pub enum SceneSource {
    /// A COLMAP sparse model folder (`cameras`, `images`, `points3D`, `.bin` or `.txt`).
    Colmap(PathBuf),
    /// A Bundle Adjustment in the Large problem file.
    Bal(PathBuf),
    /// A Bundler v0.3 `bundle.out` file.
    Bundler(PathBuf),
    /// An OpenSfM dataset folder (or its `reconstruction.json`), with `tracks.csv`.
    OpenSfm(PathBuf),
}

impl SceneSource {
    /// Reads and validates the scene, with its keypoints in the orientation
    /// [`Image::ranked_keypoints`](crate::scene::Image::ranked_keypoints) expects
    /// ([`Scene::orient_keypoint_order`]).
    pub fn load(&self) -> anyhow::Result<Scene> {
        let mut scene = self.load_as_stored()?;
        scene.orient_keypoint_order(RANK_BLOCK);
        Ok(scene)
    }

    /// Reads and validates the scene, keypoints in the order the files store them.
    pub fn load_as_stored(&self) -> anyhow::Result<Scene> {
        let scene = match self {
            SceneSource::Colmap(dir) => colmap::read_model(dir)?,
            SceneSource::Bal(path) => bal::read_bal(path)?,
            SceneSource::Bundler(path) => bundler::read_bundler(path)?,
            SceneSource::OpenSfm(path) => opensfm::read_opensfm(path)?,
        };
        scene.validate()?;
        Ok(scene)
    }

    /// Scene name `<kind>/<stem>`: the model folder for COLMAP (its parent scene folder for
    /// the `<scene>/sparse/<n>` layout), the file stem for BAL, the folder holding a
    /// Bundler `bundle.out`, and the OpenSfM dataset folder (each reader's `scene_name`).
    pub fn name(&self) -> String {
        match self {
            SceneSource::Colmap(dir) => colmap::scene_name(dir),
            SceneSource::Bal(path) => bal::scene_name(path),
            SceneSource::Bundler(path) => bundler::scene_name(path),
            SceneSource::OpenSfm(path) => opensfm::scene_name(path),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scene_names_follow_the_source_layout() {
        let name = |s: SceneSource| s.name();
        assert_eq!(
            name(SceneSource::Colmap("/data/colmap/mouse".into())),
            "colmap/mouse"
        );
        assert_eq!(
            name(SceneSource::Colmap("/data/garden/sparse/0".into())),
            "colmap/garden"
        );
        assert_eq!(
            name(SceneSource::Bal("/d/problem-49-7776-pre.txt".into())),
            "bal/problem-49-7776-pre"
        );
        assert_eq!(
            name(SceneSource::Bundler("/data/kermit/bundle.out".into())),
            "bundler/kermit"
        );
        assert_eq!(
            name(SceneSource::OpenSfm(
                "/data/opensfm/bathtub/reconstruction.json".into()
            )),
            "opensfm/bathtub"
        );
    }
}
