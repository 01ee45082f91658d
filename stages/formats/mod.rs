//! File formats, one module each. No pipeline knowledge lives here.
pub mod canvas;
pub mod dicom;
pub mod dicom_writer;
pub mod exr_image;
pub mod lidc_xml;
pub mod mhd;
pub mod model;
pub mod obj;
pub mod png;
pub mod svg;
pub mod vdb;
pub mod xml_nesting;
