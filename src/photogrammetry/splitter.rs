//! The image splitter: several cameras that are views of one sensor.
//!
//! An image splitter (a mirror or prism arrangement in front of one camera)
//! puts two or four views of the flow side by side on one sensor. Each view
//! is calibrated as a camera of its own (its own exterior and interior
//! orientation, design paper section 4.1), with the view's size as its
//! sensor; a frame is one image that [`Splitter::split`] cuts into the
//! views, in camera order.
//!
//! Layouts (the regions are the image's halves or quadrants; width and
//! height must divide evenly, so that every view has the same size):
//!
//! - [`SplitterLayout::Quadrants`]: pyptv's splitter (`ptv.splitter: true`,
//!   its `image_split` with the order `[0, 1, 3, 2]`): camera 1 is the
//!   top-left quadrant, camera 2 the top-right, camera 3 the bottom-right
//!   and camera 4 the bottom-left (clockwise from the top left).
//! - [`SplitterLayout::LeftRight`]: camera 1 the left half, camera 2 the
//!   right half.
//! - [`SplitterLayout::TopBottom`]: camera 1 the top half, camera 2 the
//!   bottom half.

use serde::{Deserialize, Serialize};

use super::image::{GreyImage, GreyPixels};

/// How the views lie on the sensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SplitterLayout {
    /// Four quadrants, clockwise from the top left (pyptv's order).
    Quadrants,
    /// Two halves side by side: left, right.
    LeftRight,
    /// Two halves one above the other: top, bottom.
    TopBottom,
}

/// A splitter: the cameras of a calibration are views of one sensor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Splitter {
    /// Where each camera's view lies.
    pub layout: SplitterLayout,
}

/// An image the splitter's layout does not fit.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error(
    "the {layout} layout cuts an image into {columns}x{rows} equal views, but the image is \
     {width}x{height} pixels, which does not divide evenly; give the whole sensor's image \
     (twice the views' size in each direction that is split)"
)]
pub struct SplitterError {
    /// The layout's name as in the calibration JSON.
    pub layout: &'static str,
    /// Views across.
    pub columns: u32,
    /// Views down.
    pub rows: u32,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
}

impl Splitter {
    /// pyptv's four-view splitter.
    pub fn quadrants() -> Splitter {
        Splitter {
            layout: SplitterLayout::Quadrants,
        }
    }

    /// How many views (cameras) the layout has: 2 or 4.
    pub fn views(&self) -> usize {
        self.regions().len()
    }

    /// Views across and down.
    fn grid(&self) -> (u32, u32) {
        match self.layout {
            SplitterLayout::Quadrants => (2, 2),
            SplitterLayout::LeftRight => (2, 1),
            SplitterLayout::TopBottom => (1, 2),
        }
    }

    /// The layout's name as in the calibration JSON.
    pub fn name(&self) -> &'static str {
        match self.layout {
            SplitterLayout::Quadrants => "quadrants",
            SplitterLayout::LeftRight => "left_right",
            SplitterLayout::TopBottom => "top_bottom",
        }
    }

    /// Per camera, its view's (column, row) in the grid.
    fn regions(&self) -> &'static [(u32, u32)] {
        match self.layout {
            SplitterLayout::Quadrants => &[(0, 0), (1, 0), (1, 1), (0, 1)],
            SplitterLayout::LeftRight => &[(0, 0), (1, 0)],
            SplitterLayout::TopBottom => &[(0, 0), (0, 1)],
        }
    }

    /// The size of each view of a `width` x `height` image, or why the
    /// layout does not fit it.
    pub fn view_size(&self, width: u32, height: u32) -> Result<(u32, u32), SplitterError> {
        let (columns, rows) = self.grid();
        if width % columns != 0 || height % rows != 0 || width < columns || height < rows {
            return Err(SplitterError {
                layout: self.name(),
                columns,
                rows,
                width,
                height,
            });
        }
        Ok((width / columns, height / rows))
    }

    /// The size of the whole image whose views are `width` x `height`
    /// (what a frame must have), or `None` past `u32`.
    pub fn image_size(&self, width: u32, height: u32) -> Option<(u32, u32)> {
        let (columns, rows) = self.grid();
        Some((width.checked_mul(columns)?, height.checked_mul(rows)?))
    }

    /// Cuts one image into the views, in camera order.
    pub fn split(&self, image: &GreyImage) -> Result<Vec<GreyImage>, SplitterError> {
        self.view_size(image.width(), image.height())?;
        Ok((0..self.views())
            .map(|index| self.cut(image, index))
            .collect())
    }

    /// Cuts camera `index`'s view out of one image, without the others
    /// (`None` past the last view): a worker that needs one camera at a
    /// time holds the image and that view only.
    pub fn view(
        &self,
        image: &GreyImage,
        index: usize,
    ) -> Result<Option<GreyImage>, SplitterError> {
        self.view_size(image.width(), image.height())?;
        Ok((index < self.views()).then(|| self.cut(image, index)))
    }

    /// The view `index` of an image whose size fits the layout.
    fn cut(&self, image: &GreyImage, index: usize) -> GreyImage {
        let (w, h) = self
            .view_size(image.width(), image.height())
            .expect("the size was checked");
        let stride = image.width() as usize;
        let (column, row) = self.regions()[index];
        let (x0, y0) = ((column * w) as usize, (row * h) as usize);
        let rows = y0..y0 + h as usize;
        let cut = |start: usize| start + x0..start + x0 + w as usize;
        let view = match image.pixels() {
            GreyPixels::Eight(p) => GreyImage::from_u8(
                w,
                h,
                rows.flat_map(|y| p[cut(y * stride)].iter().copied())
                    .collect(),
            ),
            GreyPixels::Sixteen(p) => GreyImage::from_u16(
                w,
                h,
                rows.flat_map(|y| p[cut(y * stride)].iter().copied())
                    .collect(),
            ),
        };
        view.expect("a view of a valid image is a valid image")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An image whose every pixel tells its position: `x + 10 y`.
    fn numbered(width: u32, height: u32) -> GreyImage {
        let pixels = (0..height)
            .flat_map(|y| (0..width).map(move |x| (x + 10 * y) as u16))
            .collect();
        GreyImage::from_u16(width, height, pixels).unwrap()
    }

    #[test]
    fn quadrants_are_in_pyptvs_order_clockwise_from_the_top_left() {
        let views = Splitter::quadrants().split(&numbered(6, 4)).unwrap();
        assert_eq!(views.len(), 4);
        // The first pixel of each view: top-left (0,0), top-right (3,0),
        // bottom-right (3,2), bottom-left (0,2).
        let corners: Vec<u16> = views.iter().map(|v| v.get(0, 0).unwrap()).collect();
        assert_eq!(corners, vec![0, 3, 23, 20]);
        for view in &views {
            assert_eq!((view.width(), view.height()), (3, 2));
        }
        // The whole bottom-right view.
        let GreyPixels::Sixteen(p) = views[2].pixels() else {
            panic!("16-bit in, 16-bit out")
        };
        assert_eq!(p, &vec![23, 24, 25, 33, 34, 35]);
    }

    #[test]
    fn halves_and_eight_bit_images() {
        let image = GreyImage::from_u8(4, 2, (0..8).collect()).unwrap();
        let left_right = Splitter {
            layout: SplitterLayout::LeftRight,
        };
        let views = left_right.split(&image).unwrap();
        assert_eq!(left_right.views(), 2);
        assert_eq!(views[0].pixels(), &GreyPixels::Eight(vec![0, 1, 4, 5]));
        assert_eq!(views[1].pixels(), &GreyPixels::Eight(vec![2, 3, 6, 7]));
        let top_bottom = Splitter {
            layout: SplitterLayout::TopBottom,
        };
        let views = top_bottom.split(&image).unwrap();
        assert_eq!(views[0].pixels(), &GreyPixels::Eight(vec![0, 1, 2, 3]));
        assert_eq!(views[1].pixels(), &GreyPixels::Eight(vec![4, 5, 6, 7]));
    }

    #[test]
    fn one_view_is_the_same_as_that_view_of_the_split() {
        let image = numbered(6, 4);
        for layout in [
            SplitterLayout::Quadrants,
            SplitterLayout::LeftRight,
            SplitterLayout::TopBottom,
        ] {
            let splitter = Splitter { layout };
            let views = splitter.split(&image).unwrap();
            for (index, view) in views.iter().enumerate() {
                let one = splitter.view(&image, index).unwrap().unwrap();
                assert_eq!(one.pixels(), view.pixels(), "{layout:?} {index}");
                assert_eq!((one.width(), one.height()), (view.width(), view.height()));
            }
            assert!(splitter.view(&image, views.len()).unwrap().is_none());
        }
        assert!(Splitter::quadrants().view(&numbered(5, 4), 0).is_err());
    }

    #[test]
    fn a_layout_that_does_not_divide_the_image_is_refused() {
        let error = Splitter::quadrants().split(&numbered(5, 4)).unwrap_err();
        assert_eq!((error.width, error.columns), (5, 2));
        assert!(error.to_string().contains("5x4 pixels"), "{error}");
        // Halving a 1-pixel side gives nothing.
        let top_bottom = Splitter {
            layout: SplitterLayout::TopBottom,
        };
        assert!(top_bottom.split(&numbered(4, 1)).is_err());
    }

    #[test]
    fn the_json_form_names_the_layout() {
        let json = serde_json::to_string(&Splitter::quadrants()).unwrap();
        assert_eq!(json, r#"{"layout":"quadrants"}"#);
        assert!(serde_json::from_str::<Splitter>(r#"{"layout":"thirds"}"#).is_err());
    }
}
