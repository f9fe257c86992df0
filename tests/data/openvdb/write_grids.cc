// Writes the OpenVDB test files of tests/vdb_double_grids.py with OpenVDB's own C++ library: Debian's pyopenvdb
// wraps FloatGrid, BoolGrid and Vec3SGrid only, so a DoubleGrid (what C++ simulations write) needs C++.
//
// Build (Debian 12: libopenvdb-dev, which brings libtbb-dev, libimath-dev, libblosc-dev and Boost's headers):
//   g++ -std=c++17 -O1 write_grids.cc -o write_grids -lopenvdb -ltbb -lImath-3_1
// Run through tests/vdb_double_grids.py, which writes the arrays and the spec this program reads:
//   out PATH                                  start a file
//   grid NAME TYPE NX NY NZ I J K SX SY SZ TX TY TZ HALF RAW
//                                             a grid: TYPE double, float or int32; element [0, 0, 0] of the [z, y, x]
//                                             float64 array in RAW ("-": none) at index (I, J, K); voxel size S and
//                                             translation T; HALF 1 saves it as half precision. Zeros stay inactive
//                                             (tools::copyFromDense with tolerance 0, as pyopenvdb's copyFromArray).
//   end                                       write the file (Blosc, as io::File does by default)
#include <openvdb/openvdb.h>
#include <openvdb/tools/Dense.h>

#include <fstream>
#include <iostream>
#include <sstream>
#include <vector>

using namespace openvdb;

template <typename GridT>
GridBase::Ptr make(const std::string& name, Coord size, Coord ijk, Vec3d scale, Vec3d translation, bool half,
                   const std::vector<double>& values)
{
    using ValueT = typename GridT::ValueType;
    auto grid = GridT::create(ValueT(0));
    grid->setName(name);
    math::Mat4d m = math::Mat4d::identity();
    for (int a = 0; a < 3; ++a) {
        m[a][a] = scale[a];
        m[3][a] = translation[a];  // OpenVDB's row vectors: translation in the last row
    }
    grid->setTransform(math::Transform::createLinearTransform(m));
    if (!values.empty()) {
        tools::Dense<ValueT, tools::LayoutXYZ> dense(CoordBBox(ijk, ijk + size - Coord(1)));
        for (int z = 0; z < size.z(); ++z)
            for (int y = 0; y < size.y(); ++y)
                for (int x = 0; x < size.x(); ++x)
                    dense.setValue(x, y, z, ValueT(values[(size_t(z) * size.y() + y) * size.x() + x]));
        tools::copyFromDense(dense, *grid, ValueT(0));
    }
    grid->setSaveFloatAsHalf(half);
    return grid;
}

int main(int argc, char** argv)
{
    if (argc != 2) {
        std::cerr << "usage: write_grids SPEC\n";
        return 2;
    }
    initialize();
    std::ifstream spec(argv[1]);
    std::string line, out;
    GridPtrVec grids;
    while (std::getline(spec, line)) {
        std::istringstream in(line);
        std::string kind;
        in >> kind;
        if (kind == "out") {
            in >> out;
            grids.clear();
        } else if (kind == "grid") {
            std::string name, type, raw;
            int nx, ny, nz, i, j, k, half;
            Vec3d s, t;
            in >> name >> type >> nx >> ny >> nz >> i >> j >> k >> s[0] >> s[1] >> s[2] >> t[0] >> t[1] >> t[2] >> half
               >> raw;
            std::vector<double> values;
            if (raw != "-") {
                values.resize(size_t(nx) * ny * nz);
                std::ifstream f(raw, std::ios::binary);
                f.read(reinterpret_cast<char*>(values.data()), std::streamsize(values.size() * sizeof(double)));
                if (!f) { std::cerr << raw << ": too short\n"; return 1; }
            }
            Coord size(nx, ny, nz), ijk(i, j, k);
            if (type == "double") grids.push_back(make<DoubleGrid>(name, size, ijk, s, t, half, values));
            else if (type == "float") grids.push_back(make<FloatGrid>(name, size, ijk, s, t, half, values));
            else if (type == "int32") grids.push_back(make<Int32Grid>(name, size, ijk, s, t, half, values));
            else { std::cerr << "unknown grid type " << type << "\n"; return 1; }
        } else if (kind == "end") {
            io::File(out).write(grids);
        }
    }
    return 0;
}
