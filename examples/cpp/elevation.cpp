// rangegp from C++17 through the C ABI (capi/include/rangegp.h, library librangegp_c):
// publishes one lidar scan of flat ground over iceoryx2, then asks the daemon over Zenoh for the
// elevation at a few points and prints them.
//
// Build (after `cargo build --release -p rangegp-c`):
//   g++ -std=c++17 examples/cpp/elevation.cpp -Icapi/include -Ltarget/release -lrangegp_c
//       -Wl,-rpath,$PWD/target/release -o elevation          (one line)
// Run against a daemon (`rangegpd run`):
//   ./elevation tcp/127.0.0.1:7447 default rangegp/default/scans

#include <rangegp.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace {

// Throws with the library's reason when a call fails.
void check(RangegpStatus status, const char* what) {
  if (status != RANGEGP_STATUS_OK) {
    throw std::runtime_error(std::string(what) + " failed (" + std::to_string(status) +
                             "): " + rangegp_last_error());
  }
}

using ClientPtr = std::unique_ptr<RangegpClient, decltype(&rangegp_client_close)>;
using PublisherPtr = std::unique_ptr<RangegpPublisher, decltype(&rangegp_publisher_close)>;

uint64_t now_ns() {
  using namespace std::chrono;
  return duration_cast<nanoseconds>(system_clock::now().time_since_epoch()).count();
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 4) {
    std::fprintf(stderr, "usage: %s CONNECT MAP_ID SCAN_SERVICE\n", argv[0]);
    return 2;
  }
  try {
    RangegpClient* raw_client = nullptr;
    check(rangegp_client_open(argv[1], argv[2], 5000, &raw_client), "rangegp_client_open");
    ClientPtr client(raw_client, &rangegp_client_close);
    check(rangegp_client_wait(client.get(), 10000), "rangegp_client_wait");

    RangegpPublisher* raw_publisher = nullptr;
    check(rangegp_publisher_open(argv[3], 42, 16 * 720, &raw_publisher), "rangegp_publisher_open");
    PublisherPtr publisher(raw_publisher, &rangegp_publisher_close);

    // 16 rings from 95° to 140° below the zenith, 720 columns: flat ground 1 m below the sensor.
    std::vector<float> ranges, inclinations, azimuths;
    for (int ring = 0; ring < 16; ++ring) {
      const double inclination = (95.0 + 3.0 * ring) * M_PI / 180.0;
      for (int column = 0; column < 720; ++column) {
        inclinations.push_back(static_cast<float>(inclination));
        azimuths.push_back(static_cast<float>(-M_PI + column * M_PI / 360.0));
        ranges.push_back(static_cast<float>(1.0 / -std::cos(inclination)));
      }
    }
    RangegpScanInfo info{};
    info.stamp_ns = now_ns();
    info.position[2] = 1.0;
    info.orientation_xyzw[3] = 1.0;
    info.max_range_m = 30.0;
    info.range_noise_per_m = 0.001;
    uint64_t sequence = 0;
    check(rangegp_publish(publisher.get(), &info, ranges.data(), inclinations.data(),
                          azimuths.data(), ranges.size(), &sequence),
          "rangegp_publish");

    // The daemon fits the scan in a few milliseconds: ask until every point is answered.
    const std::vector<double> xy = {3.0, 0.0, 0.0, -4.0, -2.0, 2.0};
    const size_t n = xy.size() / 2;
    std::vector<double> z(n), variance(n);
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    for (;;) {
      const RangegpStatus status =
          rangegp_elevation(client.get(), xy.data(), n, z.data(), variance.data());
      if (status != RANGEGP_STATUS_NO_MAP) check(status, "rangegp_elevation");
      bool all = status == RANGEGP_STATUS_OK;
      for (double v : z) all = all && !std::isnan(v);
      if (all) break;
      if (std::chrono::steady_clock::now() > deadline) {
        std::fprintf(stderr, "scan %llu not answered within 10 s\n",
                     static_cast<unsigned long long>(sequence));
        return 1;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    for (size_t i = 0; i < n; ++i) {
      std::printf("elevation %.3f %.3f %.6f %.6f\n", xy[2 * i], xy[2 * i + 1], z[i],
                  std::sqrt(variance[i]));
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "%s\n", e.what());
    return 1;
  }
  return 0;
}
